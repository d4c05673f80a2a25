//! `fedvla gen-data`: scripted-expert episodes of the SO-100 sim as a LeRobot v3.0 dataset (see
//! `fedvla_workloads::datagen`).

use std::path::PathBuf;

use fedvla_sim::TaskKind;
use fedvla_workloads::datagen::{GenDataOptions, GenProgress, generate_dataset};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(clap::Args)]
pub struct Args {
    /// Successful episodes to record; seeds the expert fails on are skipped.
    #[arg(long)]
    episodes: usize,
    /// Output directory (must not hold a dataset yet).
    #[arg(long)]
    out: PathBuf,
    /// Sim seed of the first episode; later episodes take the following seeds.
    #[arg(long, default_value_t = GenDataOptions::default().seed)]
    seed: u64,
    /// Comma-separated tasks (`fedvla tasks` lists them) the episodes cycle through: episode k is of the k-th
    /// modulo their number, recorded with its own instruction as its LeRobot task. Default: cube-in-bowl.
    #[arg(long, value_delimiter = ',', value_parser = TaskKind::from_name)]
    tasks: Vec<TaskKind>,
    /// Width and height of both cameras, in pixels (even).
    #[arg(long, default_value_t = GenDataOptions::default().image_size)]
    image_size: u32,
    /// Record recoveries: the arm executes the expert's goals perturbed by a wandering offset of this
    /// standard deviation (degrees), while the dataset records the expert's goals (0: none).
    #[arg(long, default_value_t = GenDataOptions::default().action_noise_degrees)]
    action_noise: f32,
    /// Record each layout of a task whose instruction decides the goal (pick-colour) once per goal, each cube
    /// in turn the one named, instead of once for the goal its seed drew.
    #[arg(long)]
    every_goal: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.action_noise.is_finite() && args.action_noise >= 0.0,
        "--action-noise must be a non-negative number of degrees, got {}",
        args.action_noise
    );
    let opts = GenDataOptions {
        episodes: args.episodes,
        seed: args.seed,
        tasks: if args.tasks.is_empty() { GenDataOptions::default().tasks } else { args.tasks },
        image_size: args.image_size,
        action_noise_degrees: args.action_noise,
        every_goal: args.every_goal,
    };
    let bar = ProgressBar::new(args.episodes as u64);
    bar.set_style(ProgressStyle::with_template("[{bar:30}] {pos}/{len} episodes, {msg} ({elapsed}, eta {eta})")?);
    let summary = generate_dataset(&args.out, &opts, |event| match event {
        GenProgress::Frame { total_frames, .. } => bar.set_message(format!("{total_frames} frames")),
        GenProgress::EpisodeWritten { .. } => bar.inc(1),
        GenProgress::Skipped { task, seed, frames } => {
            bar.println(format!("warning: the expert failed on {task} seed {seed} ({frames} frames); skipped"));
        }
    })?;
    bar.finish_and_clear();
    println!(
        "wrote {} episodes, {} frames in {:.1} s ({:.1} frames/s) to {}",
        summary.episodes,
        summary.frames,
        summary.elapsed.as_secs_f64(),
        summary.frames_per_second(),
        summary.root.display()
    );
    Ok(())
}
