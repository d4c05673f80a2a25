//! `fedvla eval`: a policy (or the scripted expert, on any task) in the SO-100 sim over a range of seeds, with a
//! video per episode and results.json (see `fedvla_workloads::sim_eval`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use burn::tensor::Device;
use fedvla_learner::rollout::SimPolicy;
use fedvla_policy::PolicyDir;
use fedvla_sim::TaskKind;
use fedvla_workloads::datagen::ensure_unrecorded;
use fedvla_workloads::sim_eval::{
    Agent, DEFAULT_MAX_FRAMES, DEFAULT_SEED, DEFAULT_VIDEO_SIZE, RESULTS_FILE, SimEvalOptions, evaluate_in_sim,
};
use indicatif::{ProgressBar, ProgressStyle};

#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("agent").required(true).args(["policy", "expert"])))]
pub struct Args {
    /// LeRobot SmolVLA policy directory (config.json, model.safetensors, processor statistics and
    /// a backbone folder with tokenizer.json).
    #[arg(long)]
    policy: Option<PathBuf>,
    /// Evaluate the scripted expert instead of a policy.
    #[arg(long)]
    expert: bool,
    /// The task the episodes set (`fedvla tasks` lists them; default cube-in-bowl). A policy takes it repeated:
    /// episode i on the i-th modulo their number, each told its own instruction, and the episodes of a task whose
    /// instruction decides the goal (pick-colour) again told another goal's (the language check). The expert
    /// takes one.
    #[arg(long, value_parser = TaskKind::from_name)]
    task: Vec<TaskKind>,
    /// Number of episodes; episode i runs on sim seed `--seed + i`.
    #[arg(long)]
    episodes: usize,
    /// Output directory: episode_<i>.mp4 and results.json.
    #[arg(long)]
    out: PathBuf,
    /// First sim seed (training data uses seeds from 0).
    #[arg(long, default_value_t = DEFAULT_SEED)]
    seed: u64,
    /// A dataset the policy trained on (repeatable): refuse when it recorded any of the evaluation's layouts.
    #[arg(long)]
    training_data: Vec<PathBuf>,
    /// Frame budget of an episode, at 30 fps.
    #[arg(long, default_value_t = DEFAULT_MAX_FRAMES)]
    max_frames: usize,
    /// Width and height of each camera in the videos (even); 0 writes no videos.
    #[arg(long, default_value_t = DEFAULT_VIDEO_SIZE)]
    video_size: u32,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    for dataset in &args.training_data {
        ensure_unrecorded(dataset, args.seed..args.seed + args.episodes as u64)?;
    }
    let opts = SimEvalOptions {
        episodes: args.episodes,
        seed: args.seed,
        max_frames: args.max_frames,
        video_size: (args.video_size > 0).then_some(args.video_size),
    };
    let tasks = if args.task.is_empty() { vec![TaskKind::CubeInBowl] } else { args.task.clone() };
    let loaded = args.policy.as_deref().map(|dir| load_policy(dir, &tasks)).transpose()?;
    let source = args.policy.as_ref().map(|p| p.display().to_string()).unwrap_or_default();
    let agent = match (&loaded, tasks.as_slice()) {
        (Some(policy), _) => Agent::Policy { policy, source: &source },
        (None, [task]) => Agent::Expert { task: *task },
        (None, _) => anyhow::bail!("the expert is evaluated on one task at a time: give --task once"),
    };

    let bar = ProgressBar::new(args.episodes as u64);
    bar.set_style(ProgressStyle::with_template("[{bar:30}] {pos}/{len} episodes {msg} ({elapsed}, eta {eta})")?);
    let mut successes = 0;
    let started = Instant::now();
    let summary = evaluate_in_sim(agent, &opts, &args.out, |_, result| {
        successes += usize::from(result.success);
        bar.inc(1);
        bar.set_message(format!("{successes} succeeded"));
    })?;
    bar.finish_and_clear();
    let elapsed = started.elapsed();

    let frames: u64 = summary.episodes.iter().map(|e| u64::from(e.length)).sum();
    println!(
        "{}: {}/{} episodes succeeded ({:.1}%), mean length {:.1} frames",
        summary.policy,
        summary.episodes.iter().filter(|e| e.success).count(),
        summary.episodes.len(),
        summary.success_rate.unwrap_or(0.0) * 100.0,
        summary.mean_length.unwrap_or(0.0),
    );
    if summary.by_task().len() > 1 {
        for task in summary.by_task() {
            println!("  {}: {}/{} succeeded", task.task, task.successes, task.episodes);
        }
    }
    if let Some(check) = &summary.language_check {
        println!("{check}");
    }
    println!(
        "{frames} frames in {:.1} s ({:.1} ms per frame, acting, simulating and filming)",
        elapsed.as_secs_f64(),
        elapsed.as_secs_f64() * 1000.0 / frames.max(1) as f64,
    );
    println!("results in {}", args.out.join(RESULTS_FILE).display());
    if !summary.video_errors.is_empty() {
        let lines: Vec<String> =
            summary.video_errors.iter().map(|e| format!("episode {}: {}", e.episode, e.message)).collect();
        anyhow::bail!(
            "{} of {} videos could not be written (results.json is complete):\n{}",
            lines.len(),
            summary.episodes.len(),
            lines.join("\n")
        );
    }
    Ok(())
}

/// A policy directory as a sim policy of `tasks` on the CPU (burn's flex backend).
fn load_policy(dir: &std::path::Path, tasks: &[TaskKind]) -> anyhow::Result<SimPolicy> {
    let policy = PolicyDir::load(dir).with_context(|| format!("loading policy {}", dir.display()))?;
    let stats = policy.stats.clone().with_context(|| {
        format!("{}: no normalisation statistics (policy_preprocessor/postprocessor files)", dir.display())
    })?;
    let tokenizer = policy
        .tokenizer()?
        .with_context(|| format!("{}: no tokenizer.json in the policy's backbone folder", dir.display()))?;
    Ok(SimPolicy::new(&policy.cfg, &policy.weights, stats, &tokenizer, tasks, &Device::flex())?)
}
