//! Recording the SO-100 sim's scripted expert as a LeRobot v3.0 dataset: `fedvla gen-data`, and the
//! embedded default dataset a SmolVLA run records on first use.
//!
//! Successful episodes take consecutive seeds from `seed` on, episode k on task k modulo the tasks
//! asked for, recorded with its own instruction as its LeRobot task; a seed whose episode the expert
//! fails is skipped (and reported), so the dataset holds only demonstrations that solve their task.
//! Asked for every goal, a task whose instruction decides the goal records each layout once per goal
//! (its next episodes of that task), so the same first frames lead to each cube and only the words
//! tell which. One thread simulates and renders the next episode while another encodes the current
//! one (the writer encodes its two cameras in parallel): the output depends on the seed only.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use anyhow::Context;
use fedvla_aggregator::config::task_names;
use fedvla_data::{CameraSpec, DatasetSpec, DatasetWriter, Episode, Frame, RgbImage, WrittenDataset};
use fedvla_sim::{ActionNoise, Arrangement, Camera, ExpertEnd, FPS, TaskKind, drive_expert_in, render};

/// Frame budget of an episode; the expert finishes in 150-250 frames when it succeeds.
pub const MAX_EPISODE_FRAMES: u32 = 400;

#[derive(Debug, Clone, PartialEq)]
pub struct GenDataOptions {
    /// Successful episodes to record.
    pub episodes: usize,
    /// Seed of the first scene; later attempts use the following seeds.
    pub seed: u64,
    /// The tasks episodes cycle through: episode k is of `tasks[k % tasks.len()]`.
    pub tasks: Vec<TaskKind>,
    /// Width and height of both cameras (even, for yuv420p video).
    pub image_size: u32,
    /// Standard deviation, degrees, of the perturbation the arm executes the expert's goals with
    /// (recovery demonstrations, see `fedvla_sim::perturbation`); 0 records the expert as it is.
    pub action_noise_degrees: f32,
    /// Where a task's instruction decides the goal, record each of its layouts once per goal (the task's
    /// next episodes), not once for the goal its seed drew: the words are then the only input that tells
    /// a layout's episodes apart, so a policy cannot fit the opening frames without reading them.
    pub every_goal: bool,
}

impl Default for GenDataOptions {
    fn default() -> Self {
        Self {
            episodes: 50,
            seed: 0,
            tasks: vec![TaskKind::CubeInBowl],
            image_size: 256,
            action_noise_degrees: 0.0,
            every_goal: false,
        }
    }
}

/// What [`generate_dataset`] reports while it works.
#[derive(Debug, Clone, PartialEq)]
pub enum GenProgress {
    /// A frame of episode `episode` was encoded; `total_frames` counts the whole dataset so far.
    Frame { episode: usize, frame: usize, episode_length: usize, total_frames: u64 },
    /// Episode `episode` (recorded from `seed`) is written.
    EpisodeWritten { episode: usize, seed: u64, frames: usize },
    /// The expert failed on `task` of `seed` within `frames` frames; no episode was recorded from it.
    Skipped { task: TaskKind, seed: u64, frames: u32 },
}

#[derive(Debug, Clone, PartialEq)]
pub struct GenSummary {
    pub root: PathBuf,
    pub episodes: usize,
    pub frames: u64,
    /// The seed of every written episode, in episode order.
    pub seeds: Vec<u64>,
    /// Seeds the expert failed on.
    pub skipped_seeds: Vec<u64>,
    pub elapsed: Duration,
}

impl GenSummary {
    pub fn frames_per_second(&self) -> f64 {
        self.frames as f64 / self.elapsed.as_secs_f64().max(f64::EPSILON)
    }
}

/// Beside a recorded dataset's metadata: the sim seed and task of every episode, so evaluations can use layouts
/// the dataset never saw and partitions can tell where each episode's cube started (LeRobot ignores the file).
pub const SEEDS_FILE: &str = "meta/fedvla_seeds.json";

/// What [`SEEDS_FILE`] holds.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RecordedSeeds {
    /// Episode i was recorded from the scene of `seeds[i]`.
    pub seeds: Vec<u64>,
    /// Seeds the expert failed on (no episode; recording every goal, no episode of some goal of it).
    pub skipped: Vec<u64>,
    /// The perturbation the episodes were executed with, degrees (0: none).
    #[serde(default)]
    pub action_noise_degrees: f32,
    /// The tasks the episodes cycle through ([`GenDataOptions::tasks`]); left out for the first task alone, so
    /// a cube-in-bowl dataset's file is what it was before there were other tasks.
    #[serde(default = "first_task_only", skip_serializing_if = "is_first_task_only", with = "task_names")]
    pub tasks: Vec<TaskKind>,
    /// Episode i moved cube `subjects[i]` of its seed's arrangement, where the recording asked for every goal
    /// ([`GenDataOptions::every_goal`]); empty where every episode moved the cube its seed drew.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub subjects: Vec<usize>,
}

impl RecordedSeeds {
    /// The task episode `episode` was recorded on.
    pub fn task_of(&self, episode: usize) -> TaskKind {
        self.tasks[episode % self.tasks.len()]
    }

    /// What stood on the table as episode `episode` started, and the cube it moved; `None` past the
    /// recorded episodes.
    pub fn arrangement_of(&self, episode: usize) -> Option<Arrangement> {
        let arrangement = Arrangement::from_seed(self.task_of(episode), *self.seeds.get(episode)?);
        Some(match self.subjects.get(episode) {
            Some(&subject) => arrangement.with_subject(subject),
            None => arrangement,
        })
    }
}

fn first_task_only() -> Vec<TaskKind> {
    vec![TaskKind::CubeInBowl]
}

fn is_first_task_only(tasks: &[TaskKind]) -> bool {
    tasks == [TaskKind::CubeInBowl]
}

/// The seeds a dataset was recorded from, when `fedvla gen-data` (or the embedded default) recorded it.
pub fn recorded_seeds(root: &Path) -> anyhow::Result<Option<RecordedSeeds>> {
    let path = root.join(SEEDS_FILE);
    match std::fs::read(&path) {
        Ok(bytes) => {
            let recorded: RecordedSeeds =
                serde_json::from_slice(&bytes).with_context(|| format!("parsing {}", path.display()))?;
            anyhow::ensure!(!recorded.tasks.is_empty(), "{}: an empty list of tasks", path.display());
            Ok(Some(recorded))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

/// Refuses to evaluate on `seeds` when the dataset at `root` recorded any of them: a success on a layout the
/// policy was trained on measures memory, not the task. A dataset the sim did not record (no [`SEEDS_FILE`])
/// passes, as nothing can be said of its layouts.
pub fn ensure_unrecorded(root: &Path, seeds: std::ops::Range<u64>) -> anyhow::Result<()> {
    let Some(recorded) = recorded_seeds(root)? else { return Ok(()) };
    if let Some(seed) = recorded.seeds.iter().find(|s| seeds.contains(s)) {
        anyhow::bail!(
            "evaluation seeds {}..{} include seed {seed}, a layout the training dataset {} recorded (its seeds \
             reach {}): evaluate from a seed above them",
            seeds.start,
            seeds.end,
            root.display(),
            recorded.seeds.iter().max().copied().unwrap_or(0)
        );
    }
    Ok(())
}

/// The expert's episode on one seed, every frame with its state, action and camera images.
struct RecordedEpisode {
    seed: u64,
    /// The cube it moved, among its arrangement's.
    subject: usize,
    episode: Episode,
}

/// Records `opts.episodes` successful expert episodes into a new LeRobot v3.0 dataset at `out` (which
/// must not hold a dataset yet), calling `progress` on the caller's thread as the work goes on.
///
/// Gives up when the expert fails on more seeds than `max(10, opts.episodes)`: it solves nearly every
/// scene (the sim's tests require 18 of 20), so that many failures mean the sim or the expert is broken.
pub fn generate_dataset(
    out: &Path,
    opts: &GenDataOptions,
    mut progress: impl FnMut(GenProgress),
) -> anyhow::Result<GenSummary> {
    anyhow::ensure!(opts.episodes > 0, "no episodes to record");
    anyhow::ensure!(!opts.tasks.is_empty(), "no tasks to record episodes of");
    anyhow::ensure!(
        opts.image_size > 0 && opts.image_size.is_multiple_of(2),
        "image size {} must be even and non-zero (yuv420p video)",
        opts.image_size
    );
    let started = Instant::now();
    let cameras = Camera::ALL.iter().map(|c| CameraSpec::new(c.name(), opts.image_size, opts.image_size)).collect();
    let mut spec = DatasetSpec::so100(cameras);
    spec.fps = FPS;

    let (events, event_rx) = mpsc::channel::<GenProgress>();
    let frame_events = events.clone();
    let writer = DatasetWriter::create(out, spec)
        .with_context(|| format!("creating the dataset at {}", out.display()))?
        .with_progress(move |p| {
            // Sends cannot fail: the receiver is drained until every sender is gone (also below).
            let _ = frame_events.send(GenProgress::Frame {
                episode: p.episode_index,
                frame: p.episode_frames_done,
                episode_length: p.episode_length,
                total_frames: p.total_frames_written,
            });
        });
    let max_failures = opts.episodes.max(10);

    let (written, (seeds, subjects), skipped_seeds) = std::thread::scope(|scope| {
        let (episode_tx, episode_rx) = mpsc::sync_channel::<RecordedEpisode>(1);
        let recorder_events = events.clone();
        let recorder = scope.spawn(move || record_episodes(opts, max_failures, &episode_tx, &recorder_events));
        let writer_events = events;
        let encoder = scope.spawn(move || write_episodes(writer, opts.episodes, &episode_rx, &writer_events));
        // Ends once the recorder and the writer (whose progress callback holds a sender) are done.
        for event in event_rx {
            progress(event);
        }
        let recorded = recorder.join().map_err(|_| anyhow::anyhow!("the episode recorder panicked"))?;
        let written = encoder.join().map_err(|_| anyhow::anyhow!("the dataset writer panicked"))?;
        // A recorder that stops early leaves the writer short of episodes: its error is the cause.
        let skipped = recorded?;
        let (written, recorded) = written?;
        anyhow::Ok((written, recorded.into_iter().unzip::<_, _, Vec<u64>, Vec<usize>>(), skipped))
    })?;
    let record = RecordedSeeds {
        seeds: seeds.clone(),
        skipped: skipped_seeds.clone(),
        action_noise_degrees: opts.action_noise_degrees,
        tasks: opts.tasks.clone(),
        subjects: if opts.every_goal { subjects } else { Vec::new() },
    };
    let path = written.root.join(SEEDS_FILE);
    fedvla_fs::write_atomic(&path, &serde_json::to_vec_pretty(&record).expect("seeds serialize"))
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(GenSummary {
        root: written.root,
        episodes: written.total_episodes as usize,
        frames: written.total_frames,
        seeds,
        skipped_seeds,
        elapsed: started.elapsed(),
    })
}

/// Runs the expert on seeds `opts.seed..`, each on the task of the next episode to send (with
/// `opts.every_goal`, a task whose instruction decides the goal on one seed per goal of it), and sends every
/// successful episode to `episodes` until `opts.episodes` were sent; returns the seeds it skipped. Stops early
/// when the writer has hung up.
fn record_episodes(
    opts: &GenDataOptions,
    max_failures: usize,
    episodes: &mpsc::SyncSender<RecordedEpisode>,
    events: &mpsc::Sender<GenProgress>,
) -> anyhow::Result<Vec<u64>> {
    let mut skipped = Vec::new();
    // Per task, as `opts.tasks` lists them: the expert's tries and successes, for the error that gives up.
    let mut tries = vec![(0usize, 0usize); opts.tasks.len()];
    // Per task: the layout seed whose goals are not all recorded yet, and the next goal to record on it.
    let mut goals_left: Vec<Option<(u64, usize)>> = vec![None; opts.tasks.len()];
    let mut sent = 0;
    let mut next_seed = opts.seed;
    while sent < opts.episodes {
        let slot = sent % opts.tasks.len();
        let task = opts.tasks[slot];
        let (seed, arrangement) = match goals_left[slot].take() {
            Some((seed, subject)) => (seed, Arrangement::from_seed(task, seed).with_subject(subject)),
            None => {
                let seed = next_seed;
                next_seed = next_seed.checked_add(1).context("ran out of seeds")?;
                let drawn = Arrangement::from_seed(task, seed);
                // Every goal in turn, from the first cube on, instead of the one the seed drew.
                let every_goal = opts.every_goal && task.instruction_decides();
                (seed, if every_goal { drawn.with_subject(0) } else { drawn })
            }
        };
        let subject = arrangement.subject;
        if opts.every_goal && task.instruction_decides() && subject + 1 < arrangement.cubes.len() {
            goals_left[slot] = Some((seed, subject + 1));
        }
        tries[slot].0 += 1;
        match record_episode(arrangement, seed, opts.image_size, ActionNoise::degrees(opts.action_noise_degrees)) {
            Ok(episode) => {
                tries[slot].1 += 1;
                if episodes.send(RecordedEpisode { seed, subject, episode }).is_err() {
                    break;
                }
                sent += 1;
            }
            Err(frames) => {
                skipped.push(seed);
                let _ = events.send(GenProgress::Skipped { task, seed, frames });
                if skipped.len() > max_failures {
                    let tally: Vec<String> = opts
                        .tasks
                        .iter()
                        .zip(&tries)
                        .map(|(task, (tried, succeeded))| format!("{task} {succeeded} of {tried}"))
                        .collect();
                    anyhow::bail!(
                        "the expert failed on {} seeds ({}..={}) before {} episode{} succeeded; giving up. Its \
                         successes under {}° of action noise: {}. A task whose expert rarely succeeds under that \
                         noise needs less (`--action-noise`, `dataset-action-noise`) or no place in the dataset",
                        skipped.len(),
                        skipped[0],
                        seed,
                        opts.episodes,
                        if opts.episodes == 1 { "" } else { "s" },
                        opts.action_noise_degrees,
                        tally.join(", ")
                    );
                }
            }
        }
    }
    Ok(skipped)
}

/// The expert's episode on the scene of `arrangement` (its perturbation drawn from `seed`), executed with
/// `noise`, with both cameras rendered at `size`x`size` before every action (LeRobot's observation-then-action
/// order) and the scene's instruction as its task, or the frames it ran if it failed.
fn record_episode(arrangement: Arrangement, seed: u64, size: u32, noise: ActionNoise) -> Result<Episode, u32> {
    let mut frames = Vec::new();
    let end = ExpertEnd::PlanDone;
    let scene = drive_expert_in(arrangement, seed, end, MAX_EPISODE_FRAMES, noise, |scene, action| {
        let images = Camera::ALL
            .iter()
            .map(|&camera| RgbImage {
                width: size,
                height: size,
                data: render(scene, camera, size as usize, size as usize),
            })
            .collect();
        frames.push(Frame { state: scene.state().to_vec(), action: action.to_vec(), images });
    });
    if scene.success() { Ok(Episode { task: scene.instruction(), frames }) } else { Err(scene.frame()) }
}

/// Encodes the episodes received into `writer` and, once all `expected` arrived, finishes the dataset;
/// returns it with the episodes' seeds and the cubes they moved. Short of episodes it does not finish, so no
/// metadata marks the directory as a complete dataset.
fn write_episodes(
    mut writer: DatasetWriter,
    expected: usize,
    episodes: &mpsc::Receiver<RecordedEpisode>,
    events: &mpsc::Sender<GenProgress>,
) -> anyhow::Result<(WrittenDataset, Vec<(u64, usize)>)> {
    let mut seeds = Vec::new();
    for recorded in episodes {
        writer
            .add_episode(&recorded.episode)
            .with_context(|| format!("writing the episode of seed {}", recorded.seed))?;
        let _ = events.send(GenProgress::EpisodeWritten {
            episode: seeds.len(),
            seed: recorded.seed,
            frames: recorded.episode.frames.len(),
        });
        seeds.push((recorded.seed, recorded.subject));
    }
    anyhow::ensure!(seeds.len() == expected, "recording stopped after {} of {expected} episodes", seeds.len());
    Ok((writer.finish()?, seeds))
}
