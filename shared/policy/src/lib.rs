//! SmolVLA, LeRobot-exact, in burn: configuration and presets, weights by LeRobot key names,
//! the model (SigLIP + connector + truncated SmolLM2 + action expert), flow-matching training of
//! exactly the parameters SmolVLA trains, and the parity check against LeRobot's golden fixtures.
//!
//! The backend is chosen through burn's `Device` (flex on CPU, wgpu/WebGPU on GPUs); nothing in
//! this crate depends on which.

#![recursion_limit = "256"]

pub mod batch;
pub mod config;
pub mod error;
mod keys;
pub mod layers;
mod lerobot_config;
pub mod normalize;
pub mod parity;
pub mod policy_dir;
pub mod smolvla;
pub mod tokenizer;
pub mod train;
pub mod vision;
pub mod vlm_with_expert;
pub mod weights;

pub use batch::Batch;
pub use config::{ParamSpec, SmolVlaConfig};
pub use error::PolicyError;
pub use normalize::{FeatureStats, NormStats};
pub use policy_dir::PolicyDir;
pub use smolvla::SmolVla;
pub use tokenizer::{Tokenizer, WordTokenizer};
pub use train::{StepReport, Trainer};
pub use weights::{HostTensor, StoredDtype, WeightMap};
