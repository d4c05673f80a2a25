//! An experiment's report from its finished runs: `report.json` ([`Report`]), `report.md` (its tables: the arms,
//! and for runs of several tasks each task's figures and the language check) and the PNG plots of held-out loss
//! and sim success against the training samples consumed (mean and 95% band per arm): arms that spend the same samples
//! in different rounds (40 of 100 steps, 400 of 10, the centralized baseline's steps) share one axis.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use serde::{Deserialize, Serialize};

use super::config::{ExperimentConfig, FINAL_FILE, Mode, last_heldout, read_final};
use super::plot::{Curve, plot_curves};
use super::stats::Interval;
use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::{MetricsLine, RolloutResults, read_metrics};
use fedvla_aggregator::run_dir::CONFIG_FILE;
use fedvla_federation::{LanguageHeldOut, PrivacyReport, TaskHeldOut};

pub const REPORT_JSON: &str = "report.json";
pub const REPORT_MD: &str = "report.md";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    pub name: String,
    /// Sim episodes per run in the final evaluation, on layouts of seeds from `eval_seed` on.
    pub eval_episodes: usize,
    pub eval_seed: u64,
    pub arms: Vec<ArmReport>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArmReport {
    pub name: String,
    pub mode: Mode,
    pub seeds: Vec<u64>,
    /// The last round's figures, mean and Student-t 95% interval over seeds.
    #[serde(rename = "final")]
    pub final_: FinalFigures,
    /// Every run's final sim episodes pooled: successes of episodes, Wilson 95% interval.
    pub success_pooled: Interval,
    pub episodes: u64,
    pub successes: u64,
    /// Training samples consumed until a run's per-round sim success first reached 90% of its final success
    /// (runs that never succeed have none).
    pub samples_to_90pct: Option<Interval>,
    pub train_seconds: Interval,
    /// Mean length (frames at 30 fps) of the successful final episodes.
    pub mean_success_length: Option<f64>,
    /// Federated arms: their success over the centralized arm's, paired by seed.
    pub ratio_to_centralized: Option<Ratio>,
    /// Arms under client-level DP: the privacy their rounds spent.
    pub privacy: Option<ArmPrivacy>,
    /// Runs of several tasks: each task's last held-out figures and final sim success.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tasks: Vec<TaskReport>,
    /// The language check of every run's final evaluation, pooled.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub language_check: Option<PooledLanguageCheck>,
    /// The language check on the held-out rows at every run's last evaluated round.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heldout_language: Option<LanguageLossReport>,
}

/// One task's figures in an arm: the last round's held-out loss and action MSE (mean and Student-t interval over
/// seeds), and its final sim episodes pooled (Wilson interval).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskReport {
    pub task: String,
    pub heldout_loss: Option<Interval>,
    pub action_mse: Option<Interval>,
    pub episodes: u64,
    pub successes: u64,
    pub success_pooled: Option<Interval>,
}

/// The language checks of an arm's runs pooled: successes told the right goal and told another, Wilson intervals.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PooledLanguageCheck {
    pub task: String,
    pub episodes: u64,
    pub right_successes: u64,
    pub wrong_successes: u64,
    pub right: Interval,
    pub wrong: Interval,
}

/// The held-out language checks of an arm's runs ([`LanguageHeldOut`]): the loss told the right goal, told another,
/// and how much higher told another, paired by seed; each mean and Student-t 95% interval over seeds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LanguageLossReport {
    pub task: String,
    pub loss_told_right: Interval,
    pub loss_told_another: Interval,
    pub increase_told_another: Interval,
}

/// The privacy a DP arm's rounds spent. The accountant's epsilon depends only on the sampling rate, the noise
/// multiplier and the rounds, so every seed of an arm spends the same: this is its first seed's.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArmPrivacy {
    pub noise_multiplier: f64,
    pub sampling_rate: f64,
    pub delta: f64,
    /// Epsilon at `delta` after each round.
    pub epsilon_per_round: Vec<RoundEpsilon>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RoundEpsilon {
    pub round: u64,
    pub epsilon: f64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FinalFigures {
    pub heldout_loss: Interval,
    pub action_mse: Option<Interval>,
    pub action_l1: Option<Interval>,
    pub success_rate: Interval,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ratio {
    /// Mean and Student-t interval of the per-seed ratios.
    pub ratio: Option<Interval>,
    pub seeds_used: Vec<u64>,
    /// Seeds where the centralized run succeeded nowhere: reported, not divided by.
    pub seeds_without_centralized_success: Vec<u64>,
}

/// One run's figures, read back from its folder.
struct RunFigures {
    seed: u64,
    heldout_loss: f64,
    action_mse: Option<f64>,
    action_l1: Option<f64>,
    success_rate: f64,
    successes: u64,
    episodes: u64,
    success_lengths: Vec<f64>,
    train_seconds: f64,
    curve: Vec<CurvePoint>,
    /// Every round's privacy report, for runs under client-level DP.
    privacy: Vec<(u64, PrivacyReport)>,
    /// The last evaluated round's held-out figures per task, and the final evaluation.
    heldout_by_task: Vec<TaskHeldOut>,
    heldout_language: Option<LanguageHeldOut>,
    final_sim: RolloutResults,
}

/// One evaluated round of a run.
struct CurvePoint {
    /// Training samples consumed by the end of the round.
    samples: u64,
    heldout_loss: f64,
    /// The round's sim success rate, where it was rolled out.
    success_rate: Option<f64>,
}

fn run_figures(run: &Path, seed: u64) -> anyhow::Result<RunFigures> {
    let metrics = read_metrics(run)?;
    let samples = samples_consumed(run, &metrics)?;
    let curve: Vec<CurvePoint> = metrics
        .iter()
        .zip(samples)
        .filter_map(|(l, samples)| {
            let g = l.global.as_ref()?;
            Some(CurvePoint {
                samples,
                heldout_loss: g.eval.as_ref()?.heldout_loss,
                success_rate: g.sim.as_ref().map(|s| s.success_rate),
            })
        })
        .collect();
    let last = last_heldout(&metrics).with_context(|| format!("{}: no evaluated round", run.display()))?;
    let final_eval = read_final(run)?;
    let final_sim = final_eval.sim.with_context(|| format!("{}: no final evaluation in the sim", run.display()))?;
    let episodes = &final_sim.episodes;
    Ok(RunFigures {
        seed,
        heldout_loss: last.heldout_loss,
        action_mse: last.action_mse,
        action_l1: last.action_l1,
        success_rate: final_sim.success_rate.unwrap_or(0.0),
        successes: episodes.iter().filter(|e| e.success).count() as u64,
        episodes: episodes.len() as u64,
        success_lengths: episodes.iter().filter(|e| e.success).map(|e| f64::from(e.length)).collect(),
        train_seconds: final_eval.train_seconds,
        curve,
        privacy: metrics.iter().filter_map(|l| Some((l.round, l.privacy?))).filter(|(round, _)| *round > 0).collect(),
        heldout_by_task: last.heldout_by_task.clone(),
        heldout_language: last.heldout_language.clone(),
        final_sim,
    })
}

/// Training samples consumed by the end of each line's round: the centralized baseline writes them; a federation's
/// are its accepted clients' local steps x batch size, round by round, under the settings each round used (the
/// operator may change them mid-run).
fn samples_consumed(run: &Path, metrics: &[MetricsLine]) -> anyhow::Result<Vec<u64>> {
    Ok(samples_by_line(&RunConfig::load(&run.join(CONFIG_FILE))?, metrics))
}

fn samples_by_line(config: &RunConfig, metrics: &[MetricsLine]) -> Vec<u64> {
    let (mut steps, mut batch) = (u64::from(config.local_steps), u64::from(config.batch_size));
    let mut total = 0;
    metrics
        .iter()
        .map(|line| {
            if let Some(settings) = &line.settings {
                steps = settings.local_steps.map_or(steps, u64::from);
                batch = settings.batch_size.map_or(batch, u64::from);
            }
            total = match line.samples {
                Some(samples) => samples,
                None if line.skipped.is_some() => total,
                None => total + line.clients.iter().filter(|c| c.accepted).count() as u64 * steps * batch,
            };
            total
        })
        .collect()
}

/// Builds the report of every finished run of `config` and writes it into the experiment's folder.
pub fn write(config: &ExperimentConfig) -> anyhow::Result<Report> {
    let dir = config.dir();
    let mut figures: BTreeMap<&str, Vec<RunFigures>> = BTreeMap::new();
    for arm in &config.arms {
        let runs = config
            .seeds
            .iter()
            .filter(|&&seed| config.run_path(arm, seed).join(FINAL_FILE).exists())
            .map(|&seed| run_figures(&config.run_path(arm, seed), seed))
            .collect::<anyhow::Result<Vec<_>>>()?;
        figures.insert(&arm.name, runs);
    }
    let centralized = config.arms.iter().find(|a| a.mode == Mode::Centralized).map(|a| &figures[a.name.as_str()]);
    let mut arms = Vec::new();
    for arm in &config.arms {
        let runs = &figures[arm.name.as_str()];
        if runs.is_empty() {
            continue;
        }
        // Every figure here is at least 0.
        let of = |f: fn(&RunFigures) -> f64| {
            Interval::t(&runs.iter().map(f).collect::<Vec<_>>()).map(|i| i.within(0.0, f64::INFINITY))
        };
        let of_opt = |f: fn(&RunFigures) -> Option<f64>| {
            let values: Option<Vec<f64>> = runs.iter().map(f).collect();
            values.and_then(|v| Interval::t(&v)).map(|i| i.within(0.0, f64::INFINITY))
        };
        let (successes, episodes) = runs.iter().fold((0, 0), |(s, e), r| (s + r.successes, e + r.episodes));
        let lengths: Vec<f64> = runs.iter().flat_map(|r| r.success_lengths.iter().copied()).collect();
        let to_90: Vec<f64> = runs.iter().filter_map(samples_to_90pct).collect();
        arms.push(ArmReport {
            name: arm.name.clone(),
            mode: arm.mode,
            seeds: runs.iter().map(|r| r.seed).collect(),
            final_: FinalFigures {
                heldout_loss: of(|r| r.heldout_loss).expect("runs is not empty"),
                action_mse: of_opt(|r| r.action_mse),
                action_l1: of_opt(|r| r.action_l1),
                success_rate: of(|r| r.success_rate).expect("runs is not empty").within(0.0, 1.0),
            },
            success_pooled: Interval::wilson(successes, episodes).expect("every run has episodes"),
            episodes,
            successes,
            samples_to_90pct: Interval::t(&to_90),
            train_seconds: of(|r| r.train_seconds).expect("runs is not empty"),
            mean_success_length: (!lengths.is_empty()).then(|| lengths.iter().sum::<f64>() / lengths.len() as f64),
            ratio_to_centralized: match (arm.mode, centralized) {
                (Mode::Federated, Some(central)) => Some(ratio(runs, central)),
                _ => None,
            },
            privacy: arm_privacy(&runs[0]),
            tasks: task_reports(runs),
            language_check: pooled_language_check(runs),
            heldout_language: language_loss(runs),
        });
    }
    let report =
        Report { name: config.name.clone(), eval_episodes: config.eval_episodes, eval_seed: config.eval_seed, arms };
    let json = serde_json::to_vec_pretty(&report).expect("the report serializes");
    fedvla_aggregator::run_dir::write_atomic(&dir.join(REPORT_JSON), &json)?;
    fedvla_aggregator::run_dir::write_atomic(&dir.join(REPORT_MD), markdown(&report, config).as_bytes())?;
    let curves = |pick: fn(&CurvePoint) -> Option<f64>| -> Vec<Curve> {
        config
            .arms
            .iter()
            .filter(|a| !figures[a.name.as_str()].is_empty())
            .map(|a| {
                Curve::over_seeds(
                    &a.name,
                    figures[a.name.as_str()]
                        .iter()
                        .map(|r| r.curve.iter().filter_map(|p| Some((p.samples, pick(p)?))).collect()),
                )
            })
            .collect()
    };
    plot_curves(
        &dir.join("heldout_loss.png"),
        "held-out loss by training samples (mean, 95% band over seeds)",
        "training samples",
        "held-out loss",
        0.0..=f64::INFINITY,
        &curves(|p| Some(p.heldout_loss)),
    )?;
    plot_curves(
        &dir.join("success_rate.png"),
        "sim success by training samples (mean, 95% band over seeds)",
        "training samples",
        "success rate",
        0.0..=1.0,
        &curves(|p| p.success_rate),
    )?;
    Ok(report)
}

/// Each task's figures over an arm's runs, in the order the first run's evaluation names them; none for runs of
/// one task.
fn task_reports(runs: &[RunFigures]) -> Vec<TaskReport> {
    let mut names: Vec<String> = Vec::new();
    for run in runs {
        let tasks = run.final_sim.by_task().into_iter().map(|t| t.task);
        for name in run.heldout_by_task.iter().map(|t| t.task.clone()).chain(tasks) {
            if !names.contains(&name) {
                names.push(name);
            }
        }
    }
    if names.len() < 2 {
        return Vec::new();
    }
    names
        .into_iter()
        .map(|task| {
            let held_out: Vec<&TaskHeldOut> =
                runs.iter().filter_map(|r| r.heldout_by_task.iter().find(|t| t.task == task)).collect();
            let losses: Vec<f64> = held_out.iter().map(|t| t.heldout_loss).collect();
            let mses: Vec<f64> = held_out.iter().filter_map(|t| t.action_mse).collect();
            let (successes, episodes) = runs
                .iter()
                .flat_map(|r| r.final_sim.by_task())
                .filter(|t| t.task == task)
                .fold((0, 0), |(s, e), t| (s + t.successes, e + t.episodes));
            TaskReport {
                heldout_loss: Interval::t(&losses).map(|i| i.within(0.0, f64::INFINITY)),
                action_mse: Interval::t(&mses).map(|i| i.within(0.0, f64::INFINITY)),
                episodes,
                successes,
                success_pooled: Interval::wilson(successes, episodes),
                task,
            }
        })
        .collect()
}

/// The language checks of an arm's final evaluations added up.
fn pooled_language_check(runs: &[RunFigures]) -> Option<PooledLanguageCheck> {
    let checks: Vec<_> = runs.iter().filter_map(|r| r.final_sim.language_check.as_ref()).collect();
    let task = checks.first()?.task.clone();
    let episodes = checks.iter().map(|c| c.episodes).sum();
    let right_successes = checks.iter().map(|c| c.right_successes).sum();
    let wrong_successes = checks.iter().map(|c| c.wrong_successes).sum();
    Some(PooledLanguageCheck {
        task,
        episodes,
        right_successes,
        wrong_successes,
        right: Interval::wilson(right_successes, episodes)?,
        wrong: Interval::wilson(wrong_successes, episodes)?,
    })
}

/// The held-out language checks of an arm's runs, where every run has one.
fn language_loss(runs: &[RunFigures]) -> Option<LanguageLossReport> {
    let checks: Vec<&LanguageHeldOut> = runs.iter().map(|r| r.heldout_language.as_ref()).collect::<Option<_>>()?;
    let of = |f: fn(&LanguageHeldOut) -> f64| Interval::t(&checks.iter().map(|c| f(c)).collect::<Vec<_>>());
    Some(LanguageLossReport {
        task: checks.first()?.task.clone(),
        loss_told_right: of(|c| c.loss_told_right)?,
        loss_told_another: of(|c| c.loss_told_another)?,
        increase_told_another: of(|c| c.loss_told_another - c.loss_told_right)?,
    })
}

fn arm_privacy(run: &RunFigures) -> Option<ArmPrivacy> {
    let (_, first) = run.privacy.first()?;
    Some(ArmPrivacy {
        noise_multiplier: first.noise_multiplier,
        sampling_rate: first.sampling_rate,
        delta: first.spent.delta,
        epsilon_per_round: run
            .privacy
            .iter()
            .map(|(round, p)| RoundEpsilon { round: *round, epsilon: p.spent.epsilon })
            .collect(),
    })
}

/// Training samples consumed until the run's per-round success first reached 90% of its final success.
fn samples_to_90pct(run: &RunFigures) -> Option<f64> {
    if run.success_rate <= 0.0 {
        return None;
    }
    run.curve.iter().find(|p| p.success_rate.is_some_and(|s| s >= 0.9 * run.success_rate)).map(|p| p.samples as f64)
}

fn ratio(runs: &[RunFigures], central: &[RunFigures]) -> Ratio {
    let mut used = Vec::new();
    let mut without = Vec::new();
    let mut ratios = Vec::new();
    for run in runs {
        match central.iter().find(|c| c.seed == run.seed) {
            Some(c) if c.success_rate > 0.0 => {
                ratios.push(run.success_rate / c.success_rate);
                used.push(run.seed);
            }
            Some(_) => without.push(run.seed),
            None => {}
        }
    }
    Ratio {
        ratio: Interval::t(&ratios).map(|i| i.within(0.0, f64::INFINITY)),
        seeds_used: used,
        seeds_without_centralized_success: without,
    }
}

/// `mean [low, high]` to `digits` decimals.
pub(crate) fn interval(i: &Interval, digits: usize) -> String {
    format!("{:.d$} [{:.d$}, {:.d$}]", i.mean, i.ci95_low, i.ci95_high, d = digits)
}

/// [`interval`], or `-` where there is no figure.
pub(crate) fn optional_interval(i: Option<&Interval>, digits: usize) -> String {
    i.map_or("-".to_owned(), |i| interval(i, digits))
}

fn markdown(report: &Report, config: &ExperimentConfig) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Experiment `{}`\n", report.name);
    let _ = writeln!(
        md,
        "Seeds {:?}. Every figure is a mean with its 95% Student-t interval over seeds, but for the pooled success \
         (Wilson 95% interval over every final episode). Final sim success: {} episodes per run on layouts of seeds \
         {}.., which no dataset records. Base run configuration: `{}`.\n",
        config.seeds, report.eval_episodes, report.eval_seed, config.run_config
    );
    md.push_str("Arms, with their overrides of the base configuration:\n\n");
    for arm in &config.arms {
        let overrides = if arm.run_config.is_empty() { "none".to_owned() } else { format!("`{}`", arm.run_config) };
        let _ = writeln!(md, "- `{}` ({:?}): {overrides}", arm.name, arm.mode);
    }
    md.push('\n');
    md.push_str("| arm | held-out loss | action MSE | action L1 | sim success | success, pooled (Wilson) | federated / centralized | samples to 90% (thousands) | train time (s) | mean successful length |\n");
    md.push_str("|---|---|---|---|---|---|---|---|---|---|\n");
    for arm in &report.arms {
        let f = &arm.final_;
        let thousands = arm.samples_to_90pct.map(|i| Interval {
            mean: i.mean / 1e3,
            ci95_low: i.ci95_low / 1e3,
            ci95_high: i.ci95_high / 1e3,
        });
        let ratio = arm.ratio_to_centralized.as_ref().map_or("-".to_owned(), |r| {
            let mut s = optional_interval(r.ratio.as_ref(), 2);
            if !r.seeds_without_centralized_success.is_empty() {
                let _ = write!(s, " (seeds {:?}: centralized succeeded nowhere)", r.seeds_without_centralized_success);
            }
            s
        });
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} | {:.2} [{:.2}, {:.2}] ({}/{}) | {} | {} | {} | {} |",
            arm.name,
            interval(&f.heldout_loss, 4),
            optional_interval(f.action_mse.as_ref(), 2),
            optional_interval(f.action_l1.as_ref(), 2),
            interval(&f.success_rate, 2),
            arm.success_pooled.mean,
            arm.success_pooled.ci95_low,
            arm.success_pooled.ci95_high,
            arm.successes,
            arm.episodes,
            ratio,
            optional_interval(thousands.as_ref(), 0),
            interval(&arm.train_seconds, 0),
            arm.mean_success_length.map_or("-".to_owned(), |l| format!("{l:.0}")),
        );
    }
    md.push_str("\nPlots: `heldout_loss.png`, `success_rate.png` (against the training samples consumed; success from the runs' own rollouts).\n");
    tasks_markdown(&mut md, report);
    privacy_markdown(&mut md, report);
    md
}

/// Each task's figures per arm, and the language check of the task whose instruction decides the goal.
fn tasks_markdown(md: &mut String, report: &Report) {
    if report.arms.iter().any(|a| !a.tasks.is_empty()) {
        md.push_str(
            "\n## Per task\n\nThe last round's held-out figures on each task's rows (mean and Student-t 95% interval \
             over seeds) and the final sim episodes of each task pooled over seeds (Wilson 95% interval).\n\n",
        );
        md.push_str(
            "| arm | task | held-out loss | action MSE | sim success, pooled (Wilson) |\n|---|---|---|---|---|\n",
        );
        for arm in &report.arms {
            for t in &arm.tasks {
                let _ = writeln!(
                    md,
                    "| {} | {} | {} | {} | {} ({}/{}) |",
                    arm.name,
                    t.task,
                    optional_interval(t.heldout_loss.as_ref(), 4),
                    optional_interval(t.action_mse.as_ref(), 2),
                    optional_interval(t.success_pooled.as_ref(), 2),
                    t.successes,
                    t.episodes
                );
            }
        }
    }
    let checks: Vec<(&str, &PooledLanguageCheck)> =
        report.arms.iter().filter_map(|a| Some((a.name.as_str(), a.language_check.as_ref()?))).collect();
    let losses: Vec<(&str, &LanguageLossReport)> =
        report.arms.iter().filter_map(|a| Some((a.name.as_str(), a.heldout_language.as_ref()?))).collect();
    if checks.is_empty() && losses.is_empty() {
        return;
    }
    md.push_str(
        "\n## Language check\n\nA policy that ignores the instruction does the same told the right goal and told \
         another. In the sim: every final episode of the task whose instruction decides the goal, rolled out told \
         its own instruction and again on the same layout and noise told another goal's, success judged by the \
         episode's own goal both times. On the held-out rows of that task at the last evaluated round: the loss \
         told each row's own instruction and told another goal's, from the same frames, noise and times (mean and \
         Student-t 95% interval over seeds; the increase paired by seed).\n\n",
    );
    if !losses.is_empty() {
        md.push_str(
            "| arm | task | held-out loss told the right goal | told another goal | increase told another |\n\
             |---|---|---|---|---|\n",
        );
        for (name, l) in &losses {
            let _ = writeln!(
                md,
                "| {name} | {} | {} | {} | {} |",
                l.task,
                interval(&l.loss_told_right, 4),
                interval(&l.loss_told_another, 4),
                interval(&l.increase_told_another, 4)
            );
        }
        md.push('\n');
    }
    if checks.is_empty() {
        return;
    }
    md.push_str("| arm | task | told the right goal (Wilson) | told another goal (Wilson) |\n|---|---|---|---|\n");
    for (name, c) in checks {
        let _ = writeln!(
            md,
            "| {name} | {} | {} ({}/{}) | {} ({}/{}) |",
            c.task,
            interval(&c.right, 2),
            c.right_successes,
            c.episodes,
            interval(&c.wrong, 2),
            c.wrong_successes,
            c.episodes
        );
    }
}

/// The DP arms' privacy: their noise, and epsilon after every round (a row per round, a column per arm).
fn privacy_markdown(md: &mut String, report: &Report) {
    let dp: Vec<(&str, &ArmPrivacy)> =
        report.arms.iter().filter_map(|a| Some((a.name.as_str(), a.privacy.as_ref()?))).collect();
    let Some((_, first)) = dp.first() else { return };
    let _ = writeln!(
        md,
        "\n## Privacy spent (client-level DP-FedAvg)\n\nEpsilon at delta = {:e} after each round, by the RDP \
         accountant of the sampled Gaussian mechanism (`fedvla_federation::accountant`).\n",
        first.delta
    );
    let _ = writeln!(md, "| | {} |", dp.iter().map(|(name, _)| *name).collect::<Vec<_>>().join(" | "));
    let _ = writeln!(md, "|---|{}", "---|".repeat(dp.len()));
    let row = |label: &str, cell: &dyn Fn(&ArmPrivacy) -> String| {
        format!("| {label} | {} |\n", dp.iter().map(|(_, p)| cell(p)).collect::<Vec<_>>().join(" | "))
    };
    md.push_str(&row("noise multiplier", &|p| format!("{}", p.noise_multiplier)));
    md.push_str(&row("sampling rate", &|p| format!("{:.3}", p.sampling_rate)));
    let rounds: std::collections::BTreeSet<u64> =
        dp.iter().flat_map(|(_, p)| p.epsilon_per_round.iter().map(|e| e.round)).collect();
    for round in rounds {
        md.push_str(&row(&format!("round {round}"), &|p| {
            p.epsilon_per_round
                .iter()
                .find(|e| e.round == round)
                .map_or("-".to_owned(), |e| format!("{:.3}", e.epsilon))
        }));
    }
}

#[cfg(test)]
mod tests {
    use fedvla_aggregator::control::Settings;
    use fedvla_aggregator::records::ClientRecord;

    use super::*;

    #[test]
    fn samples_count_accepted_clients_under_each_rounds_settings() {
        let config = RunConfig::from_toml("local-steps = 10\nbatch-size = 4\n", "test").unwrap();
        let client = |accepted| ClientRecord { accepted, ..Default::default() };
        let lines = [
            // The initial model's evaluation: nothing trained yet.
            MetricsLine { round: 0, ..Default::default() },
            // Three clients of 10 steps x 4 samples.
            MetricsLine { round: 1, clients: vec![client(true); 3], ..Default::default() },
            // A skipped round adds nothing to the model.
            MetricsLine { round: 2, clients: vec![client(true)], skipped: Some("x".into()), ..Default::default() },
            // From round 3 on, 5 local steps; the refused client's samples never reach the model.
            MetricsLine {
                round: 3,
                clients: vec![client(true), client(true), client(false)],
                settings: Some(Settings { local_steps: Some(5), ..Default::default() }),
                ..Default::default()
            },
            MetricsLine { round: 4, clients: vec![client(true)], ..Default::default() },
        ];
        assert_eq!(samples_by_line(&config, &lines), [0, 120, 120, 160, 180]);
        // The centralized baseline writes its own count.
        let centralized = [0, 3000].map(|samples| MetricsLine { samples: Some(samples), ..Default::default() });
        assert_eq!(samples_by_line(&config, &centralized), [0, 3000]);
    }
}
