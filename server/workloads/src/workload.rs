//! What is federated: the one place a model plugs into the server. A workload supplies the initial trainable
//! tensors (whose names and shapes every update is checked against), the server's held-out evaluator, exporters
//! for each round's global model, and what volunteers download; [`server_parts`] makes a server of it.

use fedvla_aggregator::config::{RunConfig, StrategyKind};
use fedvla_aggregator::parts::ServerParts;
use fedvla_aggregator::registry::VolunteerOffer;
use fedvla_aggregator::run_dir::{ModelExporter, RunDir};
use fedvla_federation::{
    Adaptivity, BoxError, Bulyan, ClipNorm, ClippedUpdates, DpFedAvg, Evaluator, FedAdaptive, FedAvg, FedAvgM,
    FedMedian, FedProx, FedTrimmedAvg, Krum, NamedTensors, QFedAvg, Scaffold, Strategy, fnv1a, mix,
};

pub trait Workload {
    fn initial_model(&self) -> Result<NamedTensors, BoxError>;

    fn evaluator(&self) -> Result<Box<dyn Evaluator + Send>, BoxError>;

    /// Written into `global_model/round_N/` after `trainable.safetensors` (e.g. a LeRobot policy directory).
    fn exporters(&self) -> Vec<Box<dyn ModelExporter>>;

    /// What the server hands volunteers over HTTP: shards, policy configuration, frozen weights.
    fn volunteer_offer(&self) -> Result<VolunteerOffer, BoxError>;
}

/// The server side of `workload` under `config`: its initial model, evaluator, exporters and volunteer offer, and
/// the configured strategy.
pub fn server_parts(workload: &impl Workload, config: RunConfig, run_dir: RunDir) -> Result<ServerParts, BoxError> {
    Ok(ServerParts {
        initial: workload.initial_model()?,
        evaluator: workload.evaluator()?,
        exporters: workload.exporters(),
        volunteer: workload.volunteer_offer()?,
        strategy: strategy(&config),
        config,
        run_dir,
    })
}

/// The configured aggregation strategy, with its parameters.
pub fn strategy(c: &RunConfig) -> Box<dyn Strategy> {
    let adaptive = |rule| Box::new(FedAdaptive::new(rule, c.server_lr, c.server_beta1, c.server_beta2, c.server_tau));
    let rule: Box<dyn Strategy> = match c.strategy {
        StrategyKind::Fedavg => Box::new(FedAvg),
        StrategyKind::Fedprox => Box::new(FedProx { mu: c.proximal_mu }),
        StrategyKind::Fedavgm => Box::new(FedAvgM::new(c.server_lr, c.server_momentum)),
        StrategyKind::Fedadagrad => adaptive(Adaptivity::Adagrad),
        StrategyKind::Fedyogi => adaptive(Adaptivity::Yogi),
        StrategyKind::Fedadam => adaptive(Adaptivity::Adam),
        StrategyKind::Median => Box::new(FedMedian),
        StrategyKind::TrimmedMean => Box::new(FedTrimmedAvg { beta: c.trim_beta }),
        StrategyKind::Krum => Box::new(Krum { f: c.krum_f, keep: 1 }),
        StrategyKind::MultiKrum => Box::new(Krum { f: c.krum_f, keep: c.krum_keep }),
        StrategyKind::Bulyan => Box::new(Bulyan { f: c.krum_f }),
        StrategyKind::Scaffold => Box::new(Scaffold::new(c.server_lr, c.num_clients)),
        StrategyKind::Qfedavg => Box::new(QFedAvg { q: c.qfedavg_q, lr: c.qfedavg_lr }),
    };
    if c.dp_enabled() {
        let clip = match c.dp_clip_quantile {
            0.0 => ClipNorm::Fixed(c.dp_clip_norm),
            quantile => ClipNorm::Adaptive {
                initial: c.dp_clip_norm,
                target_quantile: quantile,
                lr: c.dp_clip_lr,
                count_stddev: c.dp_count_stddev(),
            },
        };
        let seed = mix(c.seed, fnv1a("dp-noise"));
        Box::new(DpFedAvg::new(rule, c.dp_noise_multiplier, clip, c.dp_sampling_rate(), c.dp_delta, seed))
    } else if c.clip_update_quantile > 0.0 {
        Box::new(ClippedUpdates::adaptive(rule, c.clip_update_norm, c.clip_update_quantile, c.dp_clip_lr))
    } else if c.clip_update_norm > 0.0 {
        Box::new(ClippedUpdates::fixed(rule, c.clip_update_norm))
    } else {
        rule
    }
}
