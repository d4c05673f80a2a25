//! Closing a round: the updates screened for norms far beyond those seen, the strategy's aggregate of the rest,
//! checked (finite, and finite when evaluated) and on failure formed again without the update farthest from the
//! global model, then saved and published.

use std::sync::Arc;

use bytes::Bytes;
use fedvla_federation::{AggregateError, BoxError, ErrorCode, EvalMetrics, NamedTensors, aggregate};

use super::round::{RoundState, RoundUpdate};
use super::state::{CoordinatorError, Running, blocking};
use crate::records::{GlobalMetrics, MetricsLine, timestamp};
use crate::run_dir::RunDirError;

/// Updates a round may leave out of its aggregate before it gives up and is skipped.
const MAX_DROPPED_PER_ROUND: usize = 3;

/// What became of a round's updates.
pub(super) enum Aggregated {
    /// The global model was replaced (and the strategy's state committed); `eval` is its evaluation when the
    /// round evaluates.
    Accepted { eval: Option<EvalMetrics>, contributors: Vec<u64> },
    /// Every aggregate the round could form failed: the global model stays as it was.
    Skipped { reason: String },
}

impl Running {
    /// Aggregates `updates` into the next global model and, when `evaluate`, evaluates
    /// it. A failed aggregate or evaluation (an error, or a figure that is not finite) drops the update farthest
    /// from the current global model and tries again, as long as more than `min-fit` updates remain and at most
    /// [`MAX_DROPPED_PER_ROUND`] times; after that the round is skipped. Either way the run goes on.
    pub(super) async fn aggregate_checked(
        &mut self,
        round: u64,
        mut updates: Vec<RoundUpdate>,
        evaluate: bool,
        state: &mut RoundState,
    ) -> Result<Aggregated, CoordinatorError> {
        let mut dropped = 0;
        loop {
            let strategy = Arc::clone(&self.c.strategy);
            let global = Arc::clone(&self.c.global);
            let (aggregated, back) = blocking(move || {
                let strategy = strategy.lock().expect("strategy lock");
                let step = aggregate(strategy.as_ref(), &global, updates.iter().map(RoundUpdate::contribution));
                (step, updates)
            })
            .await;
            updates = back;
            let (reason, culprit) = match aggregated {
                Ok(step) => {
                    let candidate = Arc::new(step.global);
                    let eval = match evaluate {
                        true => Some(self.evaluate(round, Arc::clone(&candidate)).await),
                        false => None,
                    };
                    match eval {
                        Some(Ok(m)) if !m.is_finite() => {
                            (format!("the aggregate evaluates to non-finite figures {m:?}"), None)
                        }
                        Some(Err(e)) => (format!("evaluating the aggregate failed: {e}"), None),
                        eval => {
                            self.c.global = candidate;
                            self.c.strategy.lock().expect("strategy lock").commit(step.state);
                            let contributors = updates.iter().map(|u| u.client_id).collect();
                            return Ok(Aggregated::Accepted { eval: eval.and_then(Result::ok), contributors });
                        }
                    }
                }
                Err(AggregateError::Mismatch { index, source }) => {
                    (format!("update {index} does not fit the model: {source}"), Some(index))
                }
                Err(e @ AggregateError::Loss { index, .. }) => (e.to_string(), Some(index)),
                Err(e) => (format!("aggregation failed: {e}"), None),
            };
            if dropped == MAX_DROPPED_PER_ROUND || updates.len() <= self.c.config.min_fit {
                return Ok(Aggregated::Skipped { reason });
            }
            let culprit = culprit.unwrap_or_else(|| farthest(&updates));
            let client_id = updates.remove(culprit).client_id;
            dropped += 1;
            tracing::warn!(round, client_id, %reason, "dropping the update farthest from the global model, re-aggregating");
            if let Some(p) = state.participants.get_mut(&client_id) {
                p.dropped = Some(reason);
            }
            self.count(ErrorCode::DroppedUpdate);
        }
    }

    /// Leaves out of the round every update whose change from the global model is more than `update-norm-factor`
    /// times the reference norm: the median of the norms of this round's updates and of the previous round's
    /// accepted ones, which a minority of volunteers scaling their changes up cannot move. Each is recorded as
    /// the client's `dropped` reason, logged and counted as [`ErrorCode::UpdateNormOutlier`].
    pub(super) fn screen_norms(
        &mut self,
        round: u64,
        updates: Vec<RoundUpdate>,
        state: &mut RoundState,
    ) -> Vec<RoundUpdate> {
        let factor = self.c.config.update_norm_factor;
        if factor == 0.0 || updates.is_empty() {
            return updates;
        }
        let mut seen: Vec<f64> = updates.iter().map(|u| u.norm).chain(self.accepted_norms.iter().copied()).collect();
        seen.sort_by(f64::total_cmp);
        let reference = seen[seen.len() / 2];
        let (kept, outliers): (Vec<_>, Vec<_>) = updates.into_iter().partition(|u| u.norm <= factor * reference);
        for update in outliers {
            let reason = format!(
                "its change from the global model has norm {:.4e}, over {factor} x the median norm {reference:.4e}",
                update.norm
            );
            tracing::warn!(round, client_id = update.client_id, %reason, "update left out of the aggregate");
            if let Some(p) = state.participants.get_mut(&update.client_id) {
                p.dropped = Some(reason);
            }
            self.count(ErrorCode::UpdateNormOutlier);
        }
        kept
    }

    pub(super) async fn evaluate(&mut self, round: u64, model: Arc<NamedTensors>) -> Result<EvalMetrics, BoxError> {
        let evaluator = Arc::clone(&self.c.evaluator);
        let metrics = blocking(move || evaluator.lock().expect("evaluator lock").evaluate(&model)).await?;
        tracing::info!(round, ?metrics, "global model evaluated");
        Ok(metrics)
    }

    /// Saves the round's model (its exporters roll it out in the sim) and the strategy's state, appends its
    /// metrics line, then publishes the model for download. Returns the metrics line as written.
    pub(super) async fn persist(
        &mut self,
        round: u64,
        mut line: MetricsLine,
        eval: Option<EvalMetrics>,
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
        let (line, bytes) = blocking(move || -> Result<_, RunDirError> {
            let sim = run_dir.save_model(round, &global, &state, &exporters, &config)?;
            line.global = (eval.is_some() || sim.is_some()).then_some(GlobalMetrics { eval, sim });
            run_dir.append_metrics(&line)?;
            let bytes = global.to_safetensors().map_err(|source| RunDirError::Model { round, source })?;
            Ok((line, bytes))
        })
        .await?;
        let published = self.c.model_tx.borrow().next(round, Bytes::from(bytes));
        self.c.model_tx.send_replace(Arc::new(published));
        self.c.completed = Some(round);
        self.c.status_tx.send_modify(|s| s.completed_rounds = round);
        tracing::info!(round, "round completed");
        Ok(line)
    }
}

/// Index of the update farthest (Euclidean) from the round's global model, by the norm measured as it arrived:
/// after a failed aggregate, the likeliest culprit.
fn farthest(updates: &[RoundUpdate]) -> usize {
    (0..updates.len()).max_by(|&a, &b| updates[a].norm.total_cmp(&updates[b].norm)).unwrap_or(0)
}
