//! Writing LeRobot v3.0 datasets: episodes of frames in, the exact v3.0 layout out (meta/info.json,
//! meta/stats.json, meta/tasks.parquet, meta/episodes/*.parquet, data/*.parquet, one H.264 mp4 per camera
//! per file), with LeRobot's file rollover by size and a progress callback for the CLI.

use std::path::{Path, PathBuf};

mod layout;

pub use layout::{CameraSpec, DatasetSpec, SO100_JOINTS};
use layout::{EpisodeRecord, FilePosition};

use crate::error::{DataError, Result};
use crate::info::{self, CHUNKS_SIZE, CODEBASE_VERSION_V30, DATA_PATH_V30, DatasetInfo, Features, VIDEO_PATH_V30};
use crate::stats::{DatasetStats, FeatureStats};
use crate::table;
use crate::video::{CameraVideoWriter, RgbImage};

/// One time step: joint state, commanded action and one image per camera (in `DatasetSpec::cameras` order).
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub state: Vec<f32>,
    pub action: Vec<f32>,
    pub images: Vec<RgbImage>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Episode {
    pub task: String,
    pub frames: Vec<Frame>,
}

/// Reported after every frame is encoded.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WriteProgress {
    pub episode_index: usize,
    /// Frames of this episode done so far (1-based count).
    pub episode_frames_done: usize,
    pub episode_length: usize,
    pub total_frames_written: u64,
}

/// What [`DatasetWriter::finish`] wrote.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WrittenDataset {
    pub root: PathBuf,
    pub total_episodes: u64,
    pub total_frames: u64,
    pub total_tasks: u64,
}

/// Rows of the data file being filled.
#[derive(Default)]
struct DataRows {
    action: Vec<f32>,
    state: Vec<f32>,
    timestamp: Vec<f32>,
    frame_index: Vec<i64>,
    episode_index: Vec<i64>,
    index: Vec<i64>,
    task_index: Vec<i64>,
}

impl DataRows {
    fn len(&self) -> usize {
        self.index.len()
    }

    /// Uncompressed size: a conservative stand-in for the parquet size when deciding rollover.
    fn approx_bytes(&self) -> u64 {
        ((self.action.len() + self.state.len() + self.timestamp.len()) * 4 + self.len() * 32) as u64
    }
}

struct CameraStream {
    spec: CameraSpec,
    position: FilePosition,
    writer: Option<CameraVideoWriter>,
}

pub type ProgressCallback = Box<dyn FnMut(&WriteProgress) + Send>;

/// Writes a LeRobot v3.0 dataset episode by episode.
pub struct DatasetWriter {
    root: PathBuf,
    spec: DatasetSpec,
    features: Features,
    tasks: Vec<String>,
    rows: DataRows,
    data_position: FilePosition,
    cameras: Vec<CameraStream>,
    episodes: Vec<EpisodeRecord>,
    total_frames: u64,
    progress: Option<ProgressCallback>,
}

impl DatasetWriter {
    /// Prepares an empty dataset directory at `root` (created if needed; it must not hold a dataset).
    pub fn create(root: impl AsRef<Path>, spec: DatasetSpec) -> Result<Self> {
        let root = root.as_ref().to_path_buf();
        let info_path = root.join("meta/info.json");
        if info_path.exists() {
            return Err(DataError::InvalidInput(format!(
                "{} already exists; refusing to overwrite a dataset",
                info_path.display()
            )));
        }
        if spec.fps == 0 || spec.joint_names.is_empty() {
            return Err(DataError::InvalidInput("fps and joint_names must be non-zero/non-empty".into()));
        }
        // LeRobot refuses datasets whose rollover sizes are not positive.
        if spec.data_files_size_in_mb == 0 || spec.video_files_size_in_mb == 0 {
            return Err(DataError::InvalidInput(
                "data_files_size_in_mb and video_files_size_in_mb must be positive".into(),
            ));
        }
        for cam in &spec.cameras {
            if !cam.width.is_multiple_of(2) || !cam.height.is_multiple_of(2) || cam.width == 0 || cam.height == 0 {
                return Err(DataError::InvalidInput(format!(
                    "camera {} is {}x{}; yuv420p needs even sizes",
                    cam.name, cam.width, cam.height
                )));
            }
        }
        std::fs::create_dir_all(&root).map_err(|e| DataError::io(&root, e))?;
        let features = layout::build_features(&spec);
        let cameras = spec
            .cameras
            .iter()
            .map(|c| CameraStream { spec: c.clone(), position: FilePosition::default(), writer: None })
            .collect();
        Ok(Self {
            root,
            spec,
            features,
            tasks: Vec::new(),
            rows: DataRows::default(),
            data_position: FilePosition::default(),
            cameras,
            episodes: Vec::new(),
            total_frames: 0,
            progress: None,
        })
    }

    /// Calls `callback` after every frame written (the CLI draws its progress bar from it).
    pub fn with_progress(mut self, callback: impl FnMut(&WriteProgress) + Send + 'static) -> Self {
        self.progress = Some(Box::new(callback));
        self
    }

    pub fn features(&self) -> &Features {
        &self.features
    }

    /// Appends one episode: data rows, camera frames and the episode's stats.
    pub fn add_episode(&mut self, episode: &Episode) -> Result<()> {
        self.validate(episode)?;
        let episode_index = self.episodes.len();
        let task_index = match self.tasks.iter().position(|t| *t == episode.task) {
            Some(i) => i,
            None => {
                self.tasks.push(episode.task.clone());
                self.tasks.len() - 1
            }
        };
        let fps = f64::from(self.spec.fps);
        let dataset_from_index = self.total_frames;
        let mut video_starts = Vec::with_capacity(self.cameras.len());
        for cam in &mut self.cameras {
            if cam.writer.is_none() {
                let path = info::v30_path(
                    &self.root,
                    VIDEO_PATH_V30,
                    cam.position.chunk,
                    cam.position.file,
                    Some(&cam.spec.key()),
                );
                cam.writer = Some(CameraVideoWriter::create(
                    &path,
                    cam.spec.width,
                    cam.spec.height,
                    self.spec.fps,
                    self.spec.video,
                )?);
            }
            let frames_before = cam.writer.as_ref().map_or(0, CameraVideoWriter::frame_count);
            video_starts.push((cam.position, frames_before));
        }
        let mut histograms = vec![[[0u64; 256]; 3]; self.cameras.len()];
        for (frame_index, frame) in episode.frames.iter().enumerate() {
            let global_index = self.total_frames as i64;
            self.rows.action.extend_from_slice(&frame.action);
            self.rows.state.extend_from_slice(&frame.state);
            self.rows.timestamp.push((frame_index as f64 / fps) as f32);
            self.rows.frame_index.push(frame_index as i64);
            self.rows.episode_index.push(episode_index as i64);
            self.rows.index.push(global_index);
            self.rows.task_index.push(task_index as i64);
            // Cameras encode in parallel: H.264 encoding is most of the writer's time.
            let camera_results: Vec<Result<()>> = std::thread::scope(|scope| {
                let handles: Vec<_> = self
                    .cameras
                    .iter_mut()
                    .zip(&frame.images)
                    .zip(histograms.iter_mut())
                    .map(|((cam, image), hist)| {
                        scope.spawn(move || -> Result<()> {
                            if let Some(writer) = cam.writer.as_mut() {
                                writer.push_frame(image)?;
                            }
                            for px in image.data.chunks_exact(3) {
                                for c in 0..3 {
                                    hist[c][px[c] as usize] += 1;
                                }
                            }
                            Ok(())
                        })
                    })
                    .collect();
                handles
                    .into_iter()
                    .map(|h| {
                        h.join().unwrap_or_else(|_| Err(DataError::Encode("a camera encoder thread panicked".into())))
                    })
                    .collect()
            });
            camera_results.into_iter().collect::<Result<Vec<()>>>()?;
            self.total_frames += 1;
            if let Some(progress) = self.progress.as_mut() {
                progress(&WriteProgress {
                    episode_index,
                    episode_frames_done: frame_index + 1,
                    episode_length: episode.frames.len(),
                    total_frames_written: self.total_frames,
                });
            }
        }
        let length = episode.frames.len();
        let videos = video_starts
            .iter()
            .map(|&(position, before)| (position, before as f64 / fps, (before + length) as f64 / fps))
            .collect();
        let stats = self.episode_stats(episode, episode_index, task_index, dataset_from_index, &histograms);
        self.episodes.push(EpisodeRecord {
            index: episode_index,
            task: episode.task.clone(),
            length,
            data_position: self.data_position,
            dataset_from_index,
            videos,
            stats,
        });
        self.roll_over_full_files()?;
        Ok(())
    }

    fn validate(&self, episode: &Episode) -> Result<()> {
        if episode.frames.is_empty() {
            return Err(DataError::InvalidInput("an episode needs at least one frame".into()));
        }
        let dim = self.spec.joint_names.len();
        for (i, frame) in episode.frames.iter().enumerate() {
            if frame.state.len() != dim || frame.action.len() != dim {
                return Err(DataError::InvalidInput(format!(
                    "frame {i}: state has {} and action {} values, the spec has {dim} joints",
                    frame.state.len(),
                    frame.action.len()
                )));
            }
            if frame.images.len() != self.cameras.len() {
                return Err(DataError::InvalidInput(format!(
                    "frame {i}: {} images for {} cameras",
                    frame.images.len(),
                    self.cameras.len()
                )));
            }
            for (image, cam) in frame.images.iter().zip(&self.cameras) {
                if image.width != cam.spec.width
                    || image.height != cam.spec.height
                    || image.data.len() != (image.width * image.height * 3) as usize
                {
                    return Err(DataError::InvalidInput(format!(
                        "frame {i}: camera {} image is {}x{} ({} bytes), expected {}x{} RGB",
                        cam.spec.name,
                        image.width,
                        image.height,
                        image.data.len(),
                        cam.spec.width,
                        cam.spec.height
                    )));
                }
            }
        }
        Ok(())
    }

    /// Stats of every feature over this episode, in `features` order.
    fn episode_stats(
        &self,
        episode: &Episode,
        episode_index: usize,
        task_index: usize,
        from: u64,
        histograms: &[[[u64; 256]; 3]],
    ) -> Vec<FeatureStats> {
        let dim = self.spec.joint_names.len();
        let n = episode.frames.len();
        let fps = f64::from(self.spec.fps);
        let rows = |pick: &dyn Fn(&Frame) -> &[f32]| -> Vec<Vec<f64>> {
            episode.frames.iter().map(|f| pick(f).iter().map(|&v| f64::from(v)).collect()).collect()
        };
        let scalar = |value: &dyn Fn(usize) -> f64| -> FeatureStats {
            FeatureStats::from_rows(&(0..n).map(|i| vec![value(i)]).collect::<Vec<_>>(), 1)
        };
        let mut camera = histograms.iter();
        self.features
            .0
            .iter()
            .map(|(key, feature)| match key.as_str() {
                "action" => FeatureStats::from_rows(&rows(&|f| &f.action), dim),
                "observation.state" => FeatureStats::from_rows(&rows(&|f| &f.state), dim),
                // The parquet stores float32 timestamps; stats describe the stored values.
                "timestamp" => scalar(&|i| f64::from((i as f64 / fps) as f32)),
                "frame_index" => scalar(&|i| i as f64),
                "episode_index" => scalar(&|_| episode_index as f64),
                "index" => scalar(&|i| (from + i as u64) as f64),
                "task_index" => scalar(&|_| task_index as f64),
                _ if feature.dtype == "video" => {
                    let hist = camera.next().copied().unwrap_or([[0; 256]; 3]);
                    FeatureStats::from_channel_histograms(&hist, n as u64)
                }
                _ => FeatureStats::from_rows(&[], feature.width()),
            })
            .collect()
    }

    /// LeRobot's rule: once a file reaches its size limit, the next episode starts a new one.
    fn roll_over_full_files(&mut self) -> Result<()> {
        if self.rows.approx_bytes() >= self.spec.data_files_size_in_mb * 1024 * 1024 {
            self.flush_data_file()?;
            self.data_position = self.data_position.next();
        }
        for cam in &mut self.cameras {
            let full = cam
                .writer
                .as_ref()
                .is_some_and(|w| w.bytes_written() >= self.spec.video_files_size_in_mb * 1024 * 1024);
            if full && let Some(writer) = cam.writer.take() {
                writer.finish()?;
                cam.position = cam.position.next();
            }
        }
        Ok(())
    }

    fn flush_data_file(&mut self) -> Result<()> {
        if self.rows.len() == 0 {
            return Ok(());
        }
        let rows = std::mem::take(&mut self.rows);
        let dim = self.spec.joint_names.len();
        let path = info::v30_path(&self.root, DATA_PATH_V30, self.data_position.chunk, self.data_position.file, None);
        let columns: Vec<(&str, arrow_array::ArrayRef)> = vec![
            ("action", table::fixed_size_f32_list(rows.action, dim)),
            ("observation.state", table::fixed_size_f32_list(rows.state, dim)),
            ("timestamp", std::sync::Arc::new(arrow_array::Float32Array::from(rows.timestamp))),
            ("frame_index", std::sync::Arc::new(arrow_array::Int64Array::from(rows.frame_index))),
            ("episode_index", std::sync::Arc::new(arrow_array::Int64Array::from(rows.episode_index))),
            ("index", std::sync::Arc::new(arrow_array::Int64Array::from(rows.index))),
            ("task_index", std::sync::Arc::new(arrow_array::Int64Array::from(rows.task_index))),
        ];
        table::write_parquet(&path, columns, vec![("huggingface", layout::huggingface_metadata(dim))])
    }

    /// Closes the open files and writes the metadata. The dataset is complete only after this.
    pub fn finish(mut self) -> Result<WrittenDataset> {
        if self.episodes.is_empty() {
            return Err(DataError::InvalidInput("a dataset needs at least one episode".into()));
        }
        self.flush_data_file()?;
        for cam in &mut self.cameras {
            if let Some(writer) = cam.writer.take() {
                writer.finish()?;
            }
        }
        layout::write_tasks(&self.root, &self.tasks)?;
        let cameras: Vec<&CameraSpec> = self.cameras.iter().map(|c| &c.spec).collect();
        layout::write_episodes(&self.root, &self.episodes, &cameras, &self.features)?;
        let stats = self.dataset_stats();
        crate::stats::save_stats(&self.root.join("meta/stats.json"), &stats)?;
        let info = DatasetInfo {
            codebase_version: CODEBASE_VERSION_V30.into(),
            fps: self.spec.fps,
            features: self.features.clone(),
            total_episodes: self.episodes.len() as u64,
            total_frames: self.total_frames,
            total_tasks: self.tasks.len() as u64,
            total_videos: None,
            total_chunks: None,
            chunks_size: CHUNKS_SIZE,
            data_files_size_in_mb: Some(self.spec.data_files_size_in_mb),
            video_files_size_in_mb: Some(self.spec.video_files_size_in_mb),
            data_path: DATA_PATH_V30.into(),
            video_path: (!self.cameras.is_empty()).then(|| VIDEO_PATH_V30.to_string()),
            robot_type: Some(self.spec.robot_type.clone()),
            splits: [("train".to_string(), format!("0:{}", self.episodes.len()))].into_iter().collect(),
        };
        info.save(&self.root)?;
        Ok(WrittenDataset {
            root: self.root,
            total_episodes: info.total_episodes,
            total_frames: info.total_frames,
            total_tasks: info.total_tasks,
        })
    }

    fn dataset_stats(&self) -> DatasetStats {
        self.features
            .0
            .iter()
            .enumerate()
            .filter_map(|(fi, (key, _))| {
                let parts: Vec<&FeatureStats> = self.episodes.iter().map(|e| &e.stats[fi]).collect();
                FeatureStats::aggregate(&parts).map(|s| (key.clone(), s))
            })
            .collect()
    }
}
