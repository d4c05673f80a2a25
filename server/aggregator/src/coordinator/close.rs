//! Closing a round: the reasons the norm screen left updates out for, the strategy's aggregate of the updates folded
//! as they arrived, checked (finite, and finite when evaluated), then saved and published. The round holds no
//! update to leave out and form the aggregate again without (that would mean keeping them all); a failed aggregate
//! or evaluation skips the round, the global model staying as it was. What used to break an aggregate, values
//! beyond any model's, the strategies refuse as each update is folded (`dropped_update`).
//!
//! Under a compressed update encoding, the next global model is the last one plus its change as the download of
//! deltas serves it ([`encode_model_delta`]), so that a volunteer rebuilding it from the deltas holds the server's
//! model bit for bit.

use std::sync::Arc;

use bytes::Bytes;
use fedvla_federation::codec::encode_model_delta;
use fedvla_federation::{BoxError, ErrorCode, EvalMetrics, NamedTensors, conclude};

use super::round::RoundState;
use super::state::{CoordinatorError, Running, blocking};
use crate::records::{GlobalMetrics, MetricsLine, timestamp};
use crate::run_dir::RunDirError;

/// What became of a round's updates.
pub(super) enum Aggregated {
    /// The global model was replaced (and the strategy's state committed); `eval` is its evaluation when the
    /// round evaluates, `delta` its change from the last one as downloads serve it (none in f32 runs).
    Accepted { eval: Option<EvalMetrics>, contributors: Vec<u64>, delta: Option<Bytes> },
    /// The aggregate failed, or its evaluation did: the global model stays as it was.
    Skipped { reason: String },
}

impl Running {
    /// Closes the round's aggregation into the next global model and, when `evaluate`, evaluates it; an error, or
    /// a figure that is not finite, skips the round. Either way the run goes on.
    pub(super) async fn aggregate_checked(
        &mut self,
        round: u64,
        evaluate: bool,
        state: &mut RoundState,
    ) -> Result<Aggregated, CoordinatorError> {
        let aggregation = state.aggregation.take().expect("the round's aggregation is closed once");
        let strategy = Arc::clone(&self.c.strategy);
        let global = Arc::clone(&self.c.global);
        let encoding = self.c.config.encoding();
        let concluded = blocking(&self.c.jobs, move || {
            let strategy = strategy.lock().expect("strategy lock");
            let mut step =
                conclude(strategy.as_ref(), &global, aggregation).map_err(|e| format!("aggregation failed: {e}"))?;
            // The model a volunteer rebuilds from the served delta becomes the global one (see encode_model_delta).
            let delta = match encode_model_delta(&global, &step.global, encoding) {
                Ok(Some((delta, model))) => {
                    step.global = model;
                    Some(Bytes::from(delta))
                }
                Ok(None) => None,
                Err(e) => return Err(format!("the aggregate's change cannot be served as a delta: {e}")),
            };
            Ok((step, delta))
        })
        .await;
        let (step, delta) = match concluded {
            Ok(concluded) => concluded,
            Err(reason) => return Ok(Aggregated::Skipped { reason }),
        };
        let candidate = Arc::new(step.global);
        let eval = match evaluate {
            true => Some(self.evaluate(round, Arc::clone(&candidate)).await),
            false => None,
        };
        let reason = match eval {
            Some(Ok(m)) if !m.is_finite() => format!("the aggregate evaluates to non-finite figures {m:?}"),
            Some(Err(e)) => format!("evaluating the aggregate failed: {e}"),
            eval => {
                self.c.global = candidate;
                self.c.strategy.lock().expect("strategy lock").commit(step.state);
                let contributors = state.participants.iter().filter(|(_, p)| p.folded).map(|(id, _)| *id).collect();
                return Ok(Aggregated::Accepted { eval: eval.and_then(Result::ok), contributors, delta });
            }
        };
        Ok(Aggregated::Skipped { reason })
    }

    /// Writes why the norm screen left each of its outliers out, naming the round's reference norm, logs and counts
    /// each as [`ErrorCode::UpdateNormOutlier`].
    pub(super) fn record_outliers(&mut self, state: &mut RoundState) {
        let factor = self.c.config.update_norm_factor;
        let reference = self.screen.reference(&state.norms());
        let round = state.round();
        let mut outliers = 0;
        for (&client_id, p) in state.participants.iter_mut().filter(|(_, p)| p.outlier) {
            let norm = p.norm().unwrap_or(f64::NAN);
            let reason = format!(
                "its change from the global model has norm {norm:.4e}, over {factor} x the median norm {reference:.4e}"
            );
            tracing::warn!(round, client_id, %reason, "update left out of the aggregate");
            p.dropped = Some(reason);
            outliers += 1;
        }
        for _ in 0..outliers {
            self.count(ErrorCode::UpdateNormOutlier);
        }
    }

    pub(super) async fn evaluate(&mut self, round: u64, model: Arc<NamedTensors>) -> Result<EvalMetrics, BoxError> {
        let evaluator = Arc::clone(&self.c.evaluator);
        let metrics =
            blocking(&self.c.jobs, move || evaluator.lock().expect("evaluator lock").evaluate(&model)).await?;
        tracing::info!(round, ?metrics, "global model evaluated");
        Ok(metrics)
    }

    /// Saves the round's model (its exporters roll it out in the sim) and the strategy's state, appends its
    /// metrics line, then publishes the model for download, with its `delta` from the last one when it has one.
    /// Returns the metrics line as written.
    pub(super) async fn persist(
        &mut self,
        round: u64,
        mut line: MetricsLine,
        eval: Option<EvalMetrics>,
        delta: Option<Bytes>,
    ) -> Result<MetricsLine, CoordinatorError> {
        line.round = round;
        line.model_version = round;
        line.model_crc32 = self.c.global.checksum();
        line.rejections =
            std::mem::take(&mut self.round_rejections).into_iter().map(|(c, n)| (c.as_str().to_owned(), n)).collect();
        line.timestamp = timestamp();
        let (state, privacy) = {
            let strategy = self.c.strategy.lock().expect("strategy lock");
            (strategy.state(), strategy.privacy())
        };
        if let Some(p) = &privacy {
            tracing::info!(
                round,
                epsilon = p.spent.epsilon,
                delta = p.spent.delta,
                clip_norm = p.clip_norm,
                "privacy spent"
            );
        }
        line.privacy = privacy;
        let (run_dir, exporters, global, config) =
            (self.c.run_dir.clone(), Arc::clone(&self.c.exporters), Arc::clone(&self.c.global), self.c.config.clone());
        let (line, bytes) = blocking(&self.c.jobs, move || -> Result<_, RunDirError> {
            let sim = run_dir.save_model(round, &global, &state, &exporters, &config)?;
            line.global = (eval.is_some() || sim.is_some()).then_some(GlobalMetrics { eval, sim });
            run_dir.append_metrics(&line)?;
            // Disk, not data: a model that could not be removed stays, and the run goes on.
            if let Err(error) = run_dir.remove_superseded_models(config.keep_models) {
                tracing::warn!(round, %error, "could not remove the global models keep-models lets go");
            }
            let bytes = global.to_safetensors().map_err(|source| RunDirError::Model { round, source })?;
            Ok((line, bytes))
        })
        .await?;
        let published = self.c.model_tx.borrow().next(round, Bytes::from(bytes), delta);
        self.c.model_tx.send_replace(Arc::new(published));
        self.c.completed = Some(round);
        self.c.status_tx.send_modify(|s| s.completed_rounds = round);
        tracing::info!(round, "round completed");
        Ok(line)
    }
}
