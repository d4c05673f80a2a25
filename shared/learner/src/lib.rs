//! SmolVLA as the federated workload, shared by the native and the wasm client: local training
//! on a client's shard, held-out evaluation, and closed-loop rollouts of a policy in the SO-100 sim.

pub mod rollout;
