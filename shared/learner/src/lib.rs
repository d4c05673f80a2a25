//! SmolVLA as the federated workload, shared by the native and the wasm client: policy batches
//! from a client shard, local training (`LocalTrainer`), held-out evaluation (client side and the
//! server's `Evaluator`), and closed-loop rollouts of a policy in the SO-100 sim.

pub mod evaluator;
pub mod examples;
pub mod feature_cache;
pub mod heldout;
pub mod own_data;
pub mod rollout;
pub mod tensors;
pub mod trainer;
pub mod volunteer;

pub use evaluator::HeldOutEvaluator;
pub use examples::ShardExamples;
pub use trainer::SmolVlaTrainer;
