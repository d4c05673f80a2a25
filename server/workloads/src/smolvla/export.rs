//! What the server writes of each round's global model: a LeRobot policy directory, and the policy rolled out
//! and filmed in the sim.

use std::path::Path;
use std::sync::RwLock;

use burn::tensor::Device;
use fedvla_federation::{BoxError, NamedTensors, NormalizationStats};
use fedvla_learner::examples::norm_stats;
use fedvla_learner::rollout::{SimPolicy, SimTasks};
use fedvla_learner::tensors::to_weights;
use fedvla_policy::policy_dir::export;
use fedvla_policy::weights::{ParamStore, host_refs};
use fedvla_policy::{NormStats, SmolVla, SmolVlaConfig, StoredDtype, Tokenizer};
use fedvla_sim::TaskKind;

use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::SimFigures;
use fedvla_aggregator::run_dir::{ModelExporter, POLICY_DIR, ROLLOUTS_DIR};

use super::tokenizer::RunTokenizer;
use crate::sim_eval::{Agent, ROLLOUT_VIDEO_SIZE, SimEvalOptions, evaluate_in_sim};

/// Rolls each round's global model out in the sim (`global_model/round_N/rollouts/`: results.json
/// with the success rate, per task and the language check, and one MP4 per episode), on the same seeds
/// and tasks every round, for as many episodes as `rollout-episodes` says at that round (the operator
/// may change it; 0: none).
pub(super) struct SimRollouts {
    pub(super) cfg: SmolVlaConfig,
    pub(super) frozen: ParamStore,
    /// The dataset's, until the run agrees others by federated statistics.
    pub(super) stats: RwLock<NormStats>,
    pub(super) tokenizer: Tokenizer,
    /// The run's rollout tasks: episode k on the k-th.
    pub(super) tasks: Vec<TaskKind>,
}

impl ModelExporter for SimRollouts {
    fn export(
        &self,
        round: u64,
        global: &NamedTensors,
        config: &RunConfig,
        dir: &Path,
    ) -> Result<Option<SimFigures>, BoxError> {
        // Rolled out where the round is evaluated: every eval-every rounds and the last.
        let evaluated = round.is_multiple_of(config.eval_every) || round == config.num_server_rounds;
        if config.rollout_episodes == 0 || !evaluated {
            return Ok(None);
        }
        let cpu = Device::flex();
        let model =
            SmolVla::new(&self.cfg, &self.frozen.overlaid(&ParamStore::upload_owned(to_weights(global), &cpu, false)));
        let stats = self.stats.read().expect("statistics lock").clone();
        let policy = SimPolicy::from_model(model, stats, SimTasks::tokenize(&self.tasks, &self.tokenizer, &self.cfg)?)?;
        let source = format!("global model of round {round}");
        let options = SimEvalOptions {
            episodes: config.rollout_episodes,
            max_frames: config.rollout_max_frames as usize,
            video_size: Some(ROLLOUT_VIDEO_SIZE),
            ..SimEvalOptions::default()
        };
        let summary = evaluate_in_sim(
            Agent::Policy { policy: &policy, source: &source },
            &options,
            &dir.join(ROLLOUTS_DIR),
            |_, _| {},
        )
        .map_err(|e| format!("{e:#}"))?;
        let by_task: Vec<String> =
            summary.by_task().iter().map(|t| format!("{} {}/{}", t.task, t.successes, t.episodes)).collect();
        tracing::info!(
            round,
            success_rate = ?summary.success_rate,
            mean_length = ?summary.mean_length,
            by_task = by_task.join(", "),
            language_check = ?summary.language_check.as_ref().map(|c| (c.right_successes, c.wrong_successes, c.episodes)),
            "global model rolled out in the sim"
        );
        Ok(summary.figures())
    }

    fn set_norm_stats(&self, stats: &NormalizationStats) -> Result<(), BoxError> {
        *self.stats.write().expect("statistics lock") = norm_stats(stats)?;
        Ok(())
    }
}

/// Writes each round's global model as a LeRobot policy directory (`global_model/round_N/policy`).
pub(super) struct LeRobotExport {
    pub(super) cfg: SmolVlaConfig,
    pub(super) frozen: ParamStore,
    /// The dataset's, until the run agrees others by federated statistics.
    pub(super) stats: RwLock<NormStats>,
    pub(super) tokenizer: RunTokenizer,
    pub(super) dtype: StoredDtype,
}

impl ModelExporter for LeRobotExport {
    fn export(
        &self,
        _round: u64,
        global: &NamedTensors,
        _config: &RunConfig,
        dir: &Path,
    ) -> Result<Option<SimFigures>, BoxError> {
        // The frozen tensors are read from where the run holds them as they are written, never merged into a copy.
        let trainable = to_weights(global);
        let weights = self.frozen.refs().chain(host_refs(&trainable));
        let stats = self.stats.read().expect("statistics lock").clone();
        export(&dir.join(POLICY_DIR), &self.cfg, weights, &stats, self.tokenizer.backbone(), self.dtype)?;
        Ok(None)
    }

    fn set_norm_stats(&self, stats: &NormalizationStats) -> Result<(), BoxError> {
        *self.stats.write().expect("statistics lock") = norm_stats(stats)?;
        Ok(())
    }
}
