//! Reading LeRobot datasets, v3.0 and legacy v2.1: metadata (info, tasks, episodes, stats), the frame
//! table, and samples by global index with `delta_timestamps` and `<key>_is_pad` flags, camera frames coming
//! from a [`FrameSource`]. Every file is read through [`DatasetFiles`], so the same reader opens a directory on
//! disk and a folder a browser page read into memory; [`DatasetMeta`] is the first step alone (metadata only), for
//! a caller that loads the data files it names before opening the rest.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::error::{DataError, Result};
use crate::files::DatasetFiles;
use crate::info::{self, CodebaseVersion, DatasetInfo, EPISODES_PATH_V30};
use crate::stats::{DatasetStats, FeatureStats, parse_stats};
use crate::table::Table;
use crate::video::{FrameSource, RgbImage};

/// LeRobot's tolerance when matching a requested time to a video frame.
pub const VIDEO_TOLERANCE_S: f64 = 1e-4;

/// Columns every frame has; everything else float-valued is a vector feature.
const BOOKKEEPING: [&str; 5] = ["timestamp", "frame_index", "episode_index", "index", "task_index"];

/// Metadata files, relative to the dataset's root.
const INFO_PATH: &str = "meta/info.json";
const STATS_PATH: &str = "meta/stats.json";
const TASKS_PATH_V30: &str = "meta/tasks.parquet";
const EPISODES_DIR_V30: &str = "meta/episodes";
const TASKS_PATH_V21: &str = "meta/tasks.jsonl";
const EPISODES_PATH_V21: &str = "meta/episodes.jsonl";

/// Where an episode's frames of one camera live.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeVideo {
    /// The video file, relative to the dataset's root.
    pub path: PathBuf,
    /// Time of the episode's first frame inside the file (0 for v2.1's one-file-per-episode layout).
    pub from_timestamp: f64,
    pub to_timestamp: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeMeta {
    pub episode_index: usize,
    pub tasks: Vec<String>,
    pub length: usize,
    /// Global frame range `[from, to)`.
    pub dataset_from_index: usize,
    pub dataset_to_index: usize,
    /// By camera key.
    pub videos: BTreeMap<String, EpisodeVideo>,
    /// This episode's own statistics by feature (v3.0's `stats/<feature>/<stat>` columns; empty for v2.1).
    pub stats: DatasetStats,
}

/// Time offsets (seconds) to load around a frame, per feature key, e.g. `action: [0, 1/30, ..., 49/30]`.
pub type DeltaTimestamps = BTreeMap<String, Vec<f64>>;

/// One item: the frame's bookkeeping, its task, and every feature (one row, or one per delta).
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    pub index: usize,
    pub episode_index: usize,
    pub frame_index: usize,
    pub timestamp: f32,
    pub task_index: usize,
    pub task: String,
    /// Vector features (e.g. `observation.state`, `action`): one row per delta (one row without deltas).
    pub vectors: BTreeMap<String, Vec<Vec<f32>>>,
    /// Camera frames: one per delta (one without deltas).
    pub images: BTreeMap<String, Vec<RgbImage>>,
    /// `<key>_is_pad` for each key with deltas: true where the offset falls outside the episode
    /// (the value then repeats the episode's first or last frame).
    pub is_pad: BTreeMap<String, Vec<bool>>,
}

/// A dataset's metadata: what `meta/` holds, and the data files (relative to the root) its frames lie in.
pub struct DatasetMeta {
    pub info: DatasetInfo,
    pub version: CodebaseVersion,
    /// Task strings by task index.
    pub tasks: Vec<String>,
    /// In frame order.
    pub episodes: Vec<EpisodeMeta>,
    pub stats: Option<DatasetStats>,
    pub data_files: Vec<PathBuf>,
}

impl DatasetMeta {
    /// `meta/info.json`, the first file a reader reads: the dataset's schema and layout version.
    pub fn read_info(files: &dyn DatasetFiles) -> Result<(DatasetInfo, CodebaseVersion)> {
        let path = Path::new(INFO_PATH);
        DatasetInfo::from_json(&files.display_path(path), &files.read(path)?)
    }

    /// The metadata files [`DatasetMeta::read`] reads besides `meta/info.json`, for a dataset of `version` whose
    /// files `files` lists (their contents need not be loaded).
    pub fn files_to_read(version: CodebaseVersion, files: &dyn DatasetFiles) -> Result<Vec<PathBuf>> {
        let mut out = match version {
            CodebaseVersion::V30 => {
                let mut out = vec![PathBuf::from(TASKS_PATH_V30)];
                out.extend(files.list(Path::new(EPISODES_DIR_V30), "parquet")?);
                out
            }
            CodebaseVersion::V21 => vec![PathBuf::from(TASKS_PATH_V21), PathBuf::from(EPISODES_PATH_V21)],
        };
        if files.exists(Path::new(STATS_PATH)) {
            out.push(PathBuf::from(STATS_PATH));
        }
        Ok(out)
    }

    /// Reads the metadata (`meta/info.json` and [`DatasetMeta::files_to_read`]) and checks that every video file
    /// the episodes name exists.
    pub fn read(files: &dyn DatasetFiles) -> Result<Self> {
        let (info, version) = Self::read_info(files)?;
        let (tasks, episodes, data_files) = match version {
            CodebaseVersion::V30 => load_v30_meta(files, &info)?,
            CodebaseVersion::V21 => load_v21_meta(files, &info)?,
        };
        for ep in &episodes {
            for video in ep.videos.values() {
                if !files.exists(&video.path) {
                    return Err(DataError::MissingFile { path: files.display_path(&video.path) });
                }
            }
        }
        let stats_path = Path::new(STATS_PATH);
        let stats = if files.exists(stats_path) {
            Some(parse_stats(&files.display_path(stats_path), &files.read(stats_path)?)?)
        } else {
            None
        };
        Ok(Self { info, version, tasks, episodes, stats, data_files })
    }
}

/// A dataset opened for reading; the frame table (everything but the videos) is held in memory.
pub struct LeRobotDataset {
    root: PathBuf,
    info: DatasetInfo,
    version: CodebaseVersion,
    tasks: Vec<String>,
    episodes: Vec<EpisodeMeta>,
    stats: Option<DatasetStats>,
    /// Vector features by key: (values per row, flat row-major values).
    vectors: BTreeMap<String, (usize, Vec<f32>)>,
    timestamp: Vec<f32>,
    frame_index: Vec<i64>,
    episode_index: Vec<i64>,
    task_index: Vec<i64>,
    frames: Box<dyn FrameSource>,
}

impl LeRobotDataset {
    /// Opens the dataset directory at `root`, reading all metadata and frame tables and checking that every
    /// referenced data and video file exists; frames are decoded from its videos when asked for.
    #[cfg(feature = "io")]
    pub fn open(root: impl AsRef<Path>) -> Result<Self> {
        let files = std::sync::Arc::new(crate::files::DirFiles::new(root.as_ref()));
        let meta = DatasetMeta::read(&*files)?;
        Self::from_meta(meta, &*files, Box::new(crate::video::Mp4Frames::new(files.clone())))
    }

    /// The dataset of `meta` (read from `files`), reading its data files from `files`, its camera frames from
    /// `frames`.
    pub fn from_meta(meta: DatasetMeta, files: &dyn DatasetFiles, frames: Box<dyn FrameSource>) -> Result<Self> {
        let DatasetMeta { info, version, tasks, episodes, stats, data_files } = meta;
        let vector_keys: Vec<(String, usize)> = info
            .features
            .0
            .iter()
            .filter(|(k, f)| matches!(f.dtype.as_str(), "float32" | "float64") && !BOOKKEEPING.contains(&k.as_str()))
            .map(|(k, f)| (k.clone(), f.width()))
            .collect();
        let mut vectors: BTreeMap<String, (usize, Vec<f32>)> =
            vector_keys.iter().map(|(k, d)| (k.clone(), (*d, Vec::new()))).collect();
        let (mut timestamp, mut frame_index, mut episode_index, mut task_index) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for path in &data_files {
            let table = Table::read(files, path)?;
            for (key, dim) in &vector_keys {
                if let Some((_, values)) = vectors.get_mut(key) {
                    values.extend(table.f32_rows(key, *dim)?);
                }
            }
            timestamp.extend(table.f64_column("timestamp")?.into_iter().map(|t| t as f32));
            frame_index.extend(table.i64_column("frame_index")?);
            episode_index.extend(table.i64_column("episode_index")?);
            task_index.extend(table.i64_column("task_index")?);
        }
        let total: usize = episodes.iter().map(|e| e.length).sum();
        if timestamp.len() != total {
            return Err(DataError::InvalidInput(format!(
                "{}: data files hold {} rows, the episodes metadata {} frames",
                files.root().display(),
                timestamp.len(),
                total
            )));
        }
        Ok(Self {
            root: files.root().to_path_buf(),
            info,
            version,
            tasks,
            episodes,
            stats,
            vectors,
            timestamp,
            frame_index,
            episode_index,
            task_index,
            frames,
        })
    }

    /// The same dataset with its camera frames from `frames` (a page's decoded frames, once they are in).
    pub fn with_frames(self, frames: Box<dyn FrameSource>) -> Self {
        Self { frames, ..self }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }
    pub fn info(&self) -> &DatasetInfo {
        &self.info
    }

    pub fn version(&self) -> CodebaseVersion {
        self.version
    }

    pub fn fps(&self) -> u32 {
        self.info.fps
    }

    /// Task strings by task index.
    pub fn tasks(&self) -> &[String] {
        &self.tasks
    }

    pub fn episodes(&self) -> &[EpisodeMeta] {
        &self.episodes
    }

    pub fn stats(&self) -> Option<&DatasetStats> {
        self.stats.as_ref()
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.timestamp.len()
    }

    pub fn is_empty(&self) -> bool {
        self.timestamp.is_empty()
    }

    pub fn camera_keys(&self) -> Vec<String> {
        self.info.features.video_keys()
    }

    /// Row `index` of a vector feature.
    pub fn vector(&self, key: &str, index: usize) -> Option<&[f32]> {
        let (dim, values) = self.vectors.get(key)?;
        values.get(index * dim..(index + 1) * dim)
    }

    pub fn task_index(&self, index: usize) -> Option<usize> {
        self.task_index.get(index).map(|&t| t as usize)
    }

    /// The episode holding global frame `index`.
    pub fn episode_of(&self, index: usize) -> Result<&EpisodeMeta> {
        let len = self.len();
        let pos = self.episodes.partition_point(|e| e.dataset_to_index <= index);
        self.episodes
            .get(pos)
            .filter(|e| e.dataset_from_index <= index)
            .ok_or(DataError::IndexOutOfRange { index, len })
    }

    /// The video file of `camera` holding `episode`, and the times in it (seconds from the file's start) of the
    /// frames at global indices `indices` (all from that episode).
    pub fn frame_times<'a>(
        &self,
        camera: &str,
        episode: &'a EpisodeMeta,
        indices: &[usize],
    ) -> Result<(&'a Path, Vec<f64>)> {
        let video = episode.videos.get(camera).ok_or_else(|| {
            DataError::InvalidInput(format!("episode {} has no video for {camera:?}", episode.episode_index))
        })?;
        let times = indices
            .iter()
            .map(|&i| {
                let t = self.timestamp.get(i).ok_or(DataError::IndexOutOfRange { index: i, len: self.len() })?;
                Ok(video.from_timestamp + f64::from(*t))
            })
            .collect::<Result<_>>()?;
        Ok((&video.path, times))
    }

    /// The frames of `camera` at global indices `indices` (all from one episode).
    pub fn camera_frames(&self, camera: &str, episode: &EpisodeMeta, indices: &[usize]) -> Result<Vec<RgbImage>> {
        let (path, times) = self.frame_times(camera, episode, indices)?;
        self.frames.frames_at(path, &times, VIDEO_TOLERANCE_S)
    }

    /// Frame `index` with the features in `delta` loaded at those offsets (LeRobot's `__getitem__`).
    pub fn get(&self, index: usize, delta: &DeltaTimestamps) -> Result<Sample> {
        let cameras = self.camera_keys();
        if let Some(unknown) = delta.keys().find(|k| !self.vectors.contains_key(*k) && !cameras.contains(k)) {
            return Err(DataError::InvalidInput(format!(
                "delta_timestamps names {unknown:?}, which is not a vector or camera feature"
            )));
        }
        let episode = self.episode_of(index)?;
        let fps = f64::from(self.info.fps);
        let (from, to) = (episode.dataset_from_index, episode.dataset_to_index);
        // Offsets in frames, the clamped frame each reads, and whether it fell outside the episode.
        let resolve = |key: &str| -> (Vec<usize>, Option<Vec<bool>>) {
            match delta.get(key) {
                None => (vec![index], None),
                Some(offsets) => {
                    let mut rows = Vec::with_capacity(offsets.len());
                    let mut pad = Vec::with_capacity(offsets.len());
                    for &d in offsets {
                        let target = index as i64 + (d * fps).round() as i64;
                        pad.push(target < from as i64 || target >= to as i64);
                        rows.push(target.clamp(from as i64, to as i64 - 1) as usize);
                    }
                    (rows, Some(pad))
                }
            }
        };
        let mut sample = Sample {
            index,
            episode_index: self.episode_index[index] as usize,
            frame_index: self.frame_index[index] as usize,
            timestamp: self.timestamp[index],
            task_index: self.task_index[index] as usize,
            task: self.tasks.get(self.task_index[index] as usize).cloned().unwrap_or_default(),
            vectors: BTreeMap::new(),
            images: BTreeMap::new(),
            is_pad: BTreeMap::new(),
        };
        for (key, (dim, values)) in &self.vectors {
            let (rows, pad) = resolve(key);
            sample.vectors.insert(key.clone(), rows.iter().map(|&r| values[r * dim..(r + 1) * dim].to_vec()).collect());
            if let Some(pad) = pad {
                sample.is_pad.insert(format!("{key}_is_pad"), pad);
            }
        }
        for camera in cameras {
            let (rows, pad) = resolve(&camera);
            sample.images.insert(camera.clone(), self.camera_frames(&camera, episode, &rows)?);
            if let Some(pad) = pad {
                sample.is_pad.insert(format!("{camera}_is_pad"), pad);
            }
        }
        Ok(sample)
    }
}

/// One camera's `videos/<key>/*` columns of an episodes file.
struct VideoColumns {
    key: String,
    chunk: Vec<i64>,
    file: Vec<i64>,
    from_timestamp: Vec<f64>,
    to_timestamp: Vec<f64>,
}

/// v3.0: tasks.parquet, meta/episodes/**.parquet, data files referenced by the episodes.
fn load_v30_meta(
    files: &dyn DatasetFiles,
    info: &DatasetInfo,
) -> Result<(Vec<String>, Vec<EpisodeMeta>, Vec<PathBuf>)> {
    let tasks_table = Table::read(files, Path::new(TASKS_PATH_V30))?;
    let mut tasks: Vec<(i64, String)> =
        tasks_table.i64_column("task_index")?.into_iter().zip(tasks_table.string_column("task")?).collect();
    tasks.sort();
    let tasks = tasks.into_iter().map(|(_, t)| t).collect();

    let episode_files = files.list(Path::new(EPISODES_DIR_V30), "parquet")?;
    if episode_files.is_empty() {
        return Err(DataError::MissingFile { path: info::v30_path(files.root(), EPISODES_PATH_V30, 0, 0, None) });
    }
    let video_keys = info.features.video_keys();
    let video_template = info.video_path.clone().unwrap_or_else(|| info::VIDEO_PATH_V30.to_string());
    let mut episodes = Vec::new();
    let mut data_files: Vec<(i64, i64)> = Vec::new();
    for path in episode_files {
        let t = Table::read(files, &path)?;
        let index = t.i64_column("episode_index")?;
        let task_lists = t.string_list_column("tasks")?;
        let length = t.i64_column("length")?;
        let from = t.i64_column("dataset_from_index")?;
        let to = t.i64_column("dataset_to_index")?;
        let data_chunk = t.i64_column("data/chunk_index")?;
        let data_file = t.i64_column("data/file_index")?;
        let videos = video_keys
            .iter()
            .map(|key| {
                Ok(VideoColumns {
                    key: key.clone(),
                    chunk: t.i64_column(&format!("videos/{key}/chunk_index"))?,
                    file: t.i64_column(&format!("videos/{key}/file_index"))?,
                    from_timestamp: t.f64_column(&format!("videos/{key}/from_timestamp"))?,
                    to_timestamp: t.f64_column(&format!("videos/{key}/to_timestamp"))?,
                })
            })
            .collect::<Result<Vec<_>>>()?;
        let stats = episode_stats(&t, info)?;
        for row in 0..t.num_rows() {
            if !data_files.contains(&(data_chunk[row], data_file[row])) {
                data_files.push((data_chunk[row], data_file[row]));
            }
            episodes.push(EpisodeMeta {
                episode_index: index[row] as usize,
                tasks: task_lists[row].clone(),
                length: length[row] as usize,
                dataset_from_index: from[row] as usize,
                dataset_to_index: to[row] as usize,
                videos: videos
                    .iter()
                    .map(|v| {
                        let path = info::v30_path(
                            Path::new(""),
                            &video_template,
                            v.chunk[row] as u64,
                            v.file[row] as u64,
                            Some(&v.key),
                        );
                        (
                            v.key.clone(),
                            EpisodeVideo {
                                path,
                                from_timestamp: v.from_timestamp[row],
                                to_timestamp: v.to_timestamp[row],
                            },
                        )
                    })
                    .collect(),
                stats: stats.iter().filter_map(|(key, rows)| Some((key.clone(), rows[row].clone()?))).collect(),
            });
        }
    }
    episodes.sort_by_key(|e| e.dataset_from_index);
    data_files.sort();
    let data_paths = data_files
        .into_iter()
        .map(|(c, f)| info::v30_path(Path::new(""), &info.data_path, c as u64, f as u64, None))
        .collect();
    Ok((tasks, episodes, data_paths))
}

/// The per-episode statistics of one episodes file, by feature, one entry per row (`None` where a row lacks
/// mean, std, min or max).
fn episode_stats(t: &Table, info: &DatasetInfo) -> Result<BTreeMap<String, Vec<Option<FeatureStats>>>> {
    let mut columns: BTreeMap<String, BTreeMap<String, Vec<Vec<f64>>>> = BTreeMap::new();
    for name in t.column_names() {
        if let Some((feature, stat)) = name.strip_prefix("stats/").and_then(|rest| rest.rsplit_once('/')) {
            columns.entry(feature.to_owned()).or_default().insert(stat.to_owned(), t.flat_f64_rows(&name)?);
        }
    }
    let cameras = info.features.video_keys();
    Ok(columns
        .into_iter()
        .map(|(feature, by_stat)| {
            let rows = (0..t.num_rows())
                .map(|row| {
                    let get = |stat: &str| by_stat.get(stat).map(|rows| rows[row].clone());
                    let len = get("mean").map_or(0, |m| m.len());
                    // Cameras keep LeRobot's per-channel [3, 1, 1]; every other feature is a vector.
                    let shape = if cameras.contains(&feature) { vec![len, 1, 1] } else { vec![len] };
                    FeatureStats::from_named(shape, get)
                })
                .collect();
            (feature, rows)
        })
        .collect())
}

#[derive(Deserialize)]
struct TaskLine {
    task_index: i64,
    task: String,
}

#[derive(Deserialize)]
struct EpisodeLine {
    episode_index: usize,
    tasks: Vec<String>,
    length: usize,
}

/// v2.1: JSON-lines metadata, one parquet and one mp4 per camera per episode.
fn load_v21_meta(
    files: &dyn DatasetFiles,
    info: &DatasetInfo,
) -> Result<(Vec<String>, Vec<EpisodeMeta>, Vec<PathBuf>)> {
    let mut task_lines: Vec<TaskLine> = read_jsonl(files, Path::new(TASKS_PATH_V21))?;
    task_lines.sort_by_key(|t| t.task_index);
    let tasks = task_lines.into_iter().map(|t| t.task).collect();
    let mut lines: Vec<EpisodeLine> = read_jsonl(files, Path::new(EPISODES_PATH_V21))?;
    lines.sort_by_key(|e| e.episode_index);
    let video_keys = info.features.video_keys();
    let chunks_size = info.chunks_size.max(1);
    let mut episodes = Vec::with_capacity(lines.len());
    let mut data_paths = Vec::with_capacity(lines.len());
    let mut from = 0;
    for line in lines {
        let ints =
            [("episode_chunk", line.episode_index as u64 / chunks_size), ("episode_index", line.episode_index as u64)];
        data_paths.push(PathBuf::from(info::fill_template(&info.data_path, &ints, None)));
        let videos = video_keys
            .iter()
            .filter_map(|key| {
                let template = info.video_path.as_ref()?;
                let path = PathBuf::from(info::fill_template(template, &ints, Some(key)));
                let to_timestamp = line.length as f64 / f64::from(info.fps);
                Some((key.clone(), EpisodeVideo { path, from_timestamp: 0.0, to_timestamp }))
            })
            .collect();
        episodes.push(EpisodeMeta {
            episode_index: line.episode_index,
            tasks: line.tasks,
            length: line.length,
            dataset_from_index: from,
            dataset_to_index: from + line.length,
            videos,
            stats: DatasetStats::new(),
        });
        from += line.length;
    }
    Ok((tasks, episodes, data_paths))
}

fn read_jsonl<T: serde::de::DeserializeOwned>(files: &dyn DatasetFiles, path: &Path) -> Result<Vec<T>> {
    let shown = files.display_path(path);
    let bytes = files.read(path)?;
    let text = std::str::from_utf8(&bytes)
        .map_err(|e| DataError::InvalidJson { path: shown.clone(), reason: e.to_string() })?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| {
            serde_json::from_str(l)
                .map_err(|e| DataError::InvalidJson { path: shown.clone(), reason: format!("line {}: {e}", i + 1) })
        })
        .collect()
}
