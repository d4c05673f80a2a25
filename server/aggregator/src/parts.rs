//! What a server is made of: the pieces a workload supplies (initial model, evaluator, exporters, what volunteers
//! download) with the run's configuration, directory and strategy.

use fedvla_federation::{Evaluator, NamedTensors, Strategy};

use crate::config::RunConfig;
use crate::registry::VolunteerOffer;
use crate::run_dir::{ModelExporter, RunDir};

pub struct ServerParts {
    pub config: RunConfig,
    pub run_dir: RunDir,
    /// The initial global trainable tensors (ignored when the run directory already has completed rounds).
    pub initial: NamedTensors,
    pub strategy: Box<dyn Strategy>,
    pub evaluator: Box<dyn Evaluator + Send>,
    /// Run after `trainable.safetensors` is written (e.g. the LeRobot policy directory, sim rollouts).
    pub exporters: Vec<Box<dyn ModelExporter>>,
    /// What volunteers download (shards, policy, frozen weights).
    pub volunteer: VolunteerOffer,
}
