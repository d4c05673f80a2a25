//! What is federated: the one place a model plugs into the server and the native clients.
//!
//! A workload supplies the initial trainable tensors (whose names and shapes every update is checked against),
//! the server's held-out evaluator, extra exporters for each round's global model, and each client's trainer.

use fedvla_federation::{BoxError, Evaluator, LocalTrainer, NamedTensors};

use crate::run_dir::ModelExporter;
use crate::volunteer::VolunteerOffer;

pub trait Workload {
    type Trainer: LocalTrainer + Send + 'static;

    fn initial_model(&self) -> Result<NamedTensors, BoxError>;

    fn evaluator(&self) -> Result<Box<dyn Evaluator + Send>, BoxError>;

    /// Written into `global_model/round_N/` after `trainable.safetensors` (e.g. a LeRobot policy directory).
    fn exporters(&self) -> Vec<Box<dyn ModelExporter>>;

    /// What the server hands volunteers over HTTP: shards, policy configuration, frozen weights.
    fn volunteer_offer(&self) -> Result<VolunteerOffer, BoxError>;

    /// The trainer of the client holding shard `shard`.
    fn trainer(&self, shard: usize) -> Result<Self::Trainer, BoxError>;
}
