//! Aggregation strategies, one interface for all: a round opens an [`Aggregation`] from the global model its
//! clients trained from, folds their updates into it one at a time as they arrive (a streaming rule keeps a
//! running sum, a robust rule buffers what it needs, a validator sees each update), closes it into the round's
//! aggregate, and the strategy turns that into the next global model. What the strategy carries from round to
//! round (server moments, control variates, a clipping norm, the rounds a privacy accountant counts) changes only when the server commits the round, so
//! a round retried or skipped leaves it as it was, and it is saved with each round for `--resume`.

mod clipping;
mod dp;
mod interface;
mod mean;
mod qffl;
mod robust;
mod scaffold;
mod server_opt;

pub use clipping::ClippedUpdates;
pub use dp::{ClipNorm, DpFedAvg, PrivacyReport};
pub use interface::{Aggregation, Contribution, Step, Strategy, aggregate};
pub use mean::{FedAvg, FedProx, WeightedMean};
pub use qffl::QFedAvg;
pub use robust::{Bulyan, FedMedian, FedTrimmedAvg, Krum};
pub use scaffold::Scaffold;
pub use server_opt::{Adaptivity, FedAdaptive, FedAvgM};
