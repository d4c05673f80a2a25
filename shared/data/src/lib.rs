//! LeRobot datasets for the federation: writing v3.0 datasets (what the SO-100 sim records), reading
//! v3.0 and v2.1 datasets with `delta_timestamps`, splitting episodes among clients, and packing a
//! client's share into a single checksummed shard file for the browser.

pub mod error;
pub mod info;
pub mod reader;
pub mod stats;
pub mod synthetic;
mod table;
pub mod video;
pub mod writer;

pub use error::{DataError, Result};
pub use info::{CodebaseVersion, DatasetInfo, Feature, Features};
pub use reader::{DeltaTimestamps, EpisodeMeta, EpisodeVideo, LeRobotDataset, Sample};
pub use stats::{DatasetStats, FeatureStats};
pub use video::{RgbImage, VideoEncoding};
pub use writer::{CameraSpec, DatasetSpec, DatasetWriter, Episode, Frame, WriteProgress, WrittenDataset};
