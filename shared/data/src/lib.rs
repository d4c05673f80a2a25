//! LeRobot datasets for the federation: writing v3.0 datasets (what the SO-100 sim records), reading
//! v3.0 and v2.1 datasets with `delta_timestamps`, splitting episodes among clients, and packing a
//! client's share into a single checksummed shard file for the browser.
//!
//! Dataset files (reader, writer, video, building shards, synthetic episodes) need the default feature
//! `io`; without it the crate builds for wasm32 with what a browser client uses: shard parsing and
//! checksums, partitioning, stats and images.

pub mod error;
pub mod image;
pub mod info;
pub mod partition;
#[cfg(feature = "io")]
pub mod reader;
pub mod shard;
pub mod stats;
#[cfg(feature = "io")]
pub mod synthetic;
#[cfg(feature = "io")]
mod table;
#[cfg(feature = "io")]
pub mod video;
#[cfg(feature = "io")]
pub mod writer;

pub use error::{DataError, Result};
pub use image::RgbImage;
pub use info::{CodebaseVersion, DatasetInfo, Feature, Features};
#[cfg(feature = "io")]
pub use partition::episode_tasks;
pub use partition::{ClientSplit, EpisodeTask, Partition, PartitionConfig, PartitionStrategy, partition};
#[cfg(feature = "io")]
pub use reader::{DeltaTimestamps, EpisodeMeta, EpisodeVideo, LeRobotDataset, Sample};
#[cfg(feature = "io")]
pub use shard::build_shard;
pub use shard::{
    ClientShard, ShardEpisode, ShardFileManifest, ShardManifest, ShardSpec, Tokenizer, verify_shard_bytes,
    verify_shard_file,
};
pub use stats::{DatasetStats, FeatureStats};
#[cfg(feature = "io")]
pub use video::VideoEncoding;
#[cfg(feature = "io")]
pub use writer::{CameraSpec, DatasetSpec, DatasetWriter, Episode, Frame, WriteProgress, WrittenDataset};
