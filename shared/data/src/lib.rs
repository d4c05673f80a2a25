//! LeRobot datasets for the federation: writing v3.0 datasets (what the SO-100 sim records), reading
//! v3.0 and v2.1 datasets with `delta_timestamps`, splitting episodes among clients, and packing a
//! client's share into a single checksummed shard file for the browser.

pub mod error;
pub mod image;
pub mod info;
pub mod partition;
pub mod reader;
pub mod shard;
pub mod stats;
pub mod synthetic;
mod table;
pub mod video;
pub mod writer;

pub use error::{DataError, Result};
pub use info::{CodebaseVersion, DatasetInfo, Feature, Features};
pub use partition::{ClientSplit, EpisodeTask, Partition, PartitionConfig, PartitionStrategy, episode_tasks, partition};
pub use reader::{DeltaTimestamps, EpisodeMeta, EpisodeVideo, LeRobotDataset, Sample};
pub use shard::{ClientShard, ShardEpisode, ShardFileManifest, ShardManifest, ShardSpec, Tokenizer, build_shard, verify_shard_file};
pub use stats::{DatasetStats, FeatureStats};
pub use image::RgbImage;
pub use video::VideoEncoding;
pub use writer::{CameraSpec, DatasetSpec, DatasetWriter, Episode, Frame, WriteProgress, WrittenDataset};
