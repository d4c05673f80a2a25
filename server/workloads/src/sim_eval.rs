//! Evaluation in the SO-100 simulation: roll a policy (episode k on the k-th of its tasks, told that episode's
//! instruction) or the scripted expert (on any task) out over a range of seeds, film every episode (top and wrist
//! cameras side by side, H.264 mp4), run the language check on the episodes of the task whose instruction decides
//! the goal (each again, unfilmed, told another goal) and write `results.json` ([`RolloutResults`]). Used by `fedvla eval`, by the server after rounds and by experiments;
//! [`FilmedRollouts`] films a native volunteer's rollouts the same way.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::Context;
use fedvla_aggregator::records::{RolloutResults, ToldWrong, VideoError};
pub use fedvla_aggregator::run_dir::RESULTS_FILE;
use fedvla_data::RgbImage;
use fedvla_data::video::{CameraVideoWriter, VideoEncoding};
use fedvla_federation::protocol::RolloutRequest;
use fedvla_federation::{
    BoxError, Capabilities, EvalOutput, LocalTrainer, NamedTensors, RolloutEpisode, RolloutOutput, RoundTask,
    TrainOutput, Video,
};
use fedvla_learner::SmolVlaTrainer;
use fedvla_learner::rollout::{Episode, EpisodeResult, SimPolicy, run_episode};
use fedvla_learner::trainer::rollout_episode;
use fedvla_sim::{ActionNoise, Arrangement, Camera, ExpertEnd, FPS, Scene, TaskKind, drive_expert_on, render};
use std::sync::atomic::{AtomicU64, Ordering};

/// First evaluation seed: training data is generated from seeds 0.., so evaluation scenes are
/// ones no policy was trained on.
pub const DEFAULT_SEED: u64 = 10_000;
/// Frame budget of an episode (10 s at 30 fps; the expert needs 150-250 frames).
pub const DEFAULT_MAX_FRAMES: usize = 300;
/// Width and height of each camera in the videos.
pub const DEFAULT_VIDEO_SIZE: u32 = 192;
/// Camera size in the videos of the rounds' rollouts, the server's and native volunteers' (two side by side).
pub const ROLLOUT_VIDEO_SIZE: u32 = 128;

/// Who acts in the episodes.
#[derive(Clone, Copy)]
pub enum Agent<'a> {
    /// A policy; `source` (its directory, or whatever identifies it) is recorded as `policy` in
    /// results.json.
    Policy { policy: &'a SimPolicy, source: &'a str },
    /// The scripted expert on `task`, an upper reference for a policy's success rate.
    Expert { task: TaskKind },
}

impl Agent<'_> {
    /// What results.json records as `policy`: the expert's label names any task but the first (whose results said
    /// "expert" before episodes recorded their task).
    fn label(&self) -> String {
        match self {
            Agent::Policy { source, .. } => source.to_string(),
            Agent::Expert { task: TaskKind::CubeInBowl } => "expert".to_string(),
            Agent::Expert { task } => format!("expert on {task}"),
        }
    }
}

#[derive(Debug, Clone)]
pub struct SimEvalOptions {
    pub episodes: usize,
    /// Episode i runs on the scene of seed `seed + i`.
    pub seed: u64,
    pub max_frames: usize,
    /// Size of each camera in the episode videos (even); `None` films nothing.
    pub video_size: Option<u32>,
}

impl Default for SimEvalOptions {
    fn default() -> Self {
        Self { episodes: 10, seed: DEFAULT_SEED, max_frames: DEFAULT_MAX_FRAMES, video_size: Some(DEFAULT_VIDEO_SIZE) }
    }
}

/// File name of episode `i`'s video.
fn video_name(episode: usize) -> String {
    format!("episode_{episode}.mp4")
}

/// Path of episode `i`'s video in `out`.
pub fn video_path(out: &Path, episode: usize) -> PathBuf {
    out.join(video_name(episode))
}

/// Runs `opts.episodes` episodes of `agent` and writes their videos and results.json to `out`.
/// `progress` is called after every episode with its index and result.
///
/// A video that cannot be written does not stop the evaluation: the episode still counts, the
/// failure is listed in [`RolloutResults::video_errors`] (and results.json), and the partial file
/// is removed. Errors are returned for what leaves no result to report: the policy failing to act
/// or results.json not being written.
pub fn evaluate_in_sim(
    agent: Agent<'_>,
    opts: &SimEvalOptions,
    out: &Path,
    mut progress: impl FnMut(usize, &EpisodeResult),
) -> anyhow::Result<RolloutResults> {
    anyhow::ensure!(opts.episodes > 0, "no episodes to evaluate");
    if let Some(size) = opts.video_size {
        anyhow::ensure!(size > 0 && size % 2 == 0, "video size {size} must be even and non-zero (yuv420p)");
    }
    fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut episodes = Vec::with_capacity(opts.episodes);
    let mut video_errors = Vec::new();
    let mut told_wrong = Vec::new();
    for i in 0..opts.episodes {
        let seed = opts.seed + i as u64;
        let mut film = opts.video_size.map(|size| Film::start(&video_path(out, i), size));
        let mut on_frame = |scene: &Scene| {
            if let Some(film) = &mut film {
                film.record(scene);
            }
        };
        let result = match agent {
            Agent::Policy { policy, .. } => {
                let task = policy.tasks().task_of(i);
                let context = || format!("policy rollout of episode {i} ({task}, seed {seed})");
                let result = Episode::new(policy, task, seed, opts.max_frames)
                    .and_then(|episode| run_episode(episode, &mut on_frame))
                    .with_context(context)?;
                if let Some(instruction) = Arrangement::from_seed(task, seed).wrong_instruction() {
                    let wrong = Episode::told(policy, task, seed, &instruction, opts.max_frames)
                        .and_then(|episode| run_episode(episode, |_| {}))
                        .with_context(|| format!("{}, told {instruction:?}", context()))?;
                    told_wrong.push(ToldWrong {
                        episode: i as u32,
                        seed,
                        instruction,
                        success: wrong.success,
                        length: wrong.length as u32,
                    });
                }
                result
            }
            Agent::Expert { task } => run_expert(task, seed, opts.max_frames, &mut on_frame),
        };
        let filmed = film.map(Film::finish);
        if let Some(Err(message)) = &filmed {
            video_errors.push(VideoError { episode: i as u32, message: message.clone() });
        }
        progress(i, &result);
        let video = matches!(filmed, Some(Ok(()))).then(|| video_name(i));
        episodes.push(RolloutEpisode {
            episode: i as u32,
            seed: result.seed,
            success: result.success,
            length: result.length as u32,
            video,
            task: Some(result.task.name().to_owned()),
        });
    }
    let mut results = RolloutResults::of(agent.label(), None, episodes).with_language_check(told_wrong);
    results.video_errors = video_errors;
    let path = out.join(RESULTS_FILE);
    let json = serde_json::to_vec_pretty(&results).context("serialising the results")?;
    fedvla_fs::write_atomic(&path, &json).with_context(|| format!("writing {}", path.display()))?;
    Ok(results)
}

/// The scripted expert from `Scene::with_task(task, seed)`, ended like a policy episode: on success or when
/// the budget runs out.
fn run_expert(task: TaskKind, seed: u64, max_frames: usize, mut on_frame: impl FnMut(&Scene)) -> EpisodeResult {
    let scene = drive_expert_on(task, seed, ExpertEnd::Success, max_frames as u32, ActionNoise::NONE, |scene, _| {
        on_frame(scene);
    });
    on_frame(&scene);
    EpisodeResult { task, seed, success: scene.success(), length: scene.frame() as usize }
}

/// The SmolVLA volunteer as `fedvla join` and `simulate` run it: the shared trainer, its rollouts filmed as MP4
/// (as the server films its own), so every client's `evaluate/round_N/client_K/` holds a video per episode, as a
/// browser's does.
pub struct FilmedRollouts(pub SmolVlaTrainer);

/// Distinguishes the temporary files of concurrent volunteers in one process (`simulate`).
static FILMS: AtomicU64 = AtomicU64::new(0);

impl LocalTrainer for FilmedRollouts {
    fn capabilities(&self) -> Capabilities {
        self.0.capabilities()
    }

    fn set_global(&mut self, global: &NamedTensors) -> Result<(), BoxError> {
        self.0.set_global(global)
    }

    fn set_correction(&mut self, correction: &NamedTensors) -> Result<(), BoxError> {
        self.0.set_correction(correction)
    }

    fn set_norm_stats(&mut self, stats: &fedvla_federation::NormalizationStats) -> Result<(), BoxError> {
        self.0.set_norm_stats(stats)
    }

    async fn train(&mut self, task: &RoundTask) -> Result<TrainOutput, BoxError> {
        self.0.train(task).await
    }

    async fn evaluate(&mut self) -> Result<EvalOutput, BoxError> {
        self.0.evaluate().await
    }

    async fn rollout(&mut self, request: &RolloutRequest) -> Result<Vec<RolloutOutput>, BoxError> {
        let Some(policy) = self.0.sim_policy()? else { return Ok(Vec::new()) };
        let mut outputs = Vec::new();
        for episode in 0..request.episodes {
            let path = std::env::temp_dir().join(format!(
                "fedvla-rollout-{}-{}.mp4",
                std::process::id(),
                FILMS.fetch_add(1, Ordering::Relaxed)
            ));
            let mut film = Film::start(&path, ROLLOUT_VIDEO_SIZE);
            let (task, seed) = (policy.tasks().task_of(episode as usize), request.first_seed + u64::from(episode));
            let run = Episode::new(&policy, task, seed, request.max_frames as usize)?;
            let result = run_episode(run, |scene| film.record(scene))?;
            // A video that could not be made leaves the episode without one; the result still counts.
            let video = match film.finish().and_then(|()| fs::read(&path).map_err(|e| e.to_string())) {
                Ok(bytes) => Some(Video { file_name: video_name(episode as usize), mime: "video/mp4".into(), bytes }),
                Err(message) => {
                    tracing::warn!(episode, %message, "rollout video not recorded");
                    None
                }
            };
            let _ = fs::remove_file(&path);
            outputs.push(RolloutOutput { episode: rollout_episode(episode, &result), video });
        }
        Ok(outputs)
    }
}

/// One episode's video: every camera at `size`x`size`, side by side in [`Camera::ALL`] order. The
/// first error stops the filming and is kept for [`Film::finish`].
struct Film {
    path: PathBuf,
    size: u32,
    writer: Result<CameraVideoWriter, String>,
}

impl Film {
    fn start(path: &Path, size: u32) -> Self {
        let cameras = Camera::ALL.len() as u32;
        // One key frame a second: browsers seek quickly enough, and the files stay small.
        let encoding = VideoEncoding { gop: FPS, ..VideoEncoding::default() };
        let writer = CameraVideoWriter::create(path, size * cameras, size, FPS, encoding).map_err(|e| e.to_string());
        Self { path: path.to_path_buf(), size, writer }
    }

    fn record(&mut self, scene: &Scene) {
        let Ok(writer) = &mut self.writer else { return };
        let frame = side_by_side(scene, self.size as usize);
        if let Err(e) = RgbImage::new(frame.0, self.size, frame.1).and_then(|image| writer.push_frame(&image)) {
            self.writer = Err(e.to_string());
        }
    }

    fn finish(self) -> Result<(), String> {
        let result = self.writer.and_then(|w| w.finish().map_err(|e| e.to_string()));
        if result.is_err() {
            // A partial mp4 has no index (moov) and plays nowhere; leave no such file behind. The
            // file may never have been created, so a failed removal says nothing worth reporting.
            let _ = fs::remove_file(&self.path);
        }
        result.map_err(|e| format!("{}: {e}", self.path.display()))
    }
}

/// Renders every camera at `size`x`size` and lays them out left to right: (width, RGB HWC).
fn side_by_side(scene: &Scene, size: usize) -> (u32, Vec<u8>) {
    let views: Vec<Vec<u8>> = Camera::ALL.iter().map(|&camera| render(scene, camera, size, size)).collect();
    let row = size * 3;
    let mut data = Vec::with_capacity(views.len() * row * size);
    for y in 0..size {
        for view in &views {
            data.extend_from_slice(&view[y * row..(y + 1) * row]);
        }
    }
    ((views.len() * size) as u32, data)
}
