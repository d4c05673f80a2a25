//! LeRobot datasets for the federation: writing v3.0 datasets (what the SO-100 sim records), reading
//! v3.0 and v2.1 datasets with `delta_timestamps`, splitting episodes among clients, and packing a
//! client's share into a single checksummed shard for the browser.
//!
//! Feature `read` reads datasets from any [`DatasetFiles`] (a directory, or files a browser page read into
//! memory) and packs shards in memory, with camera frames from a [`video::FrameSource`]; it builds for wasm32.
//! The default feature `io` adds the file system (directories, writing datasets and shard files) and decoding
//! video natively (H.264 through OpenH264, AV1 with feature `av1`). Without either the crate is what a browser
//! client on a server shard uses: shard parsing and checksums, partitioning, stats, images.

pub mod error;
#[cfg(feature = "read")]
pub mod files;
pub mod image;
pub mod info;
pub mod partition;
#[cfg(feature = "read")]
pub mod reader;
pub mod shard;
pub mod stats;
#[cfg(feature = "io")]
pub mod synthetic;
#[cfg(feature = "read")]
mod table;
#[cfg(feature = "read")]
pub mod video;
#[cfg(feature = "io")]
pub mod writer;

pub use error::{DataError, Result};
#[cfg(feature = "io")]
pub use files::DirFiles;
#[cfg(feature = "read")]
pub use files::{DatasetFiles, MemoryFiles};
pub use image::RgbImage;
pub use info::{CodebaseVersion, DatasetInfo, Feature, Features};
#[cfg(feature = "read")]
pub use partition::episode_tasks;
pub use partition::{ClientSplit, EpisodeTask, Partition, PartitionConfig, PartitionStrategy, partition};
#[cfg(feature = "read")]
pub use reader::{DatasetMeta, DeltaTimestamps, EpisodeMeta, EpisodeVideo, LeRobotDataset, Sample};
#[cfg(feature = "io")]
pub use shard::build_shard;
#[cfg(feature = "read")]
pub use shard::pack_shard;
pub use shard::{
    ClientShard, ShardEpisode, ShardFileManifest, ShardManifest, ShardSpec, Tokenizer, verify_shard_bytes,
    verify_shard_file,
};
pub use stats::{DatasetStats, FeatureStats};
#[cfg(feature = "io")]
pub use video::VideoEncoding;
#[cfg(feature = "io")]
pub use writer::{CameraSpec, DatasetSpec, DatasetWriter, Episode, Frame, WriteProgress, WrittenDataset};
