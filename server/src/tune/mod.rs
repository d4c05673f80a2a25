//! `fedvla tune --config configs/tune/NAME.toml`: a search over a federation's hyperparameters by successive
//! halving, on the experiment's runner. Trial 0 is the base configuration, the others are drawn from the search
//! space by the search seed; each rung runs its trials as federations of its budget of rounds, on the same data and
//! run seed, judges them on the server's held-out loss, and sends the best 1/`reduction` on to the next rung, and
//! the base with them wherever it is not among them: a short rung's ranking favours what learns fast over what
//! ends best (the shipped search's first rung of 5 rounds put the main job's configuration 24th of 27, where at
//! 40 rounds it ended below the search's best), so the winner is the best at the full budget among the
//! finalists and the base, and a search never recommends what its own runs found worse than the base. The
//! winner is written whole to `best.toml` (what `fedvla simulate --config` runs). Then the best drawn finalist
//! (the winner, or the runner-up where the base won) is judged afresh against the base: both run on seeds, data
//! and sim layouts the search never used (an experiment, `judge/`), with intervals over seeds and the paired
//! difference, which says whether what the search found beats the base beyond its own selection set. Every run is
//! the runner's, so a killed search resumes where it stopped: its trials are drawn again from the same seed and
//! every finished run is read back, not run again.

pub mod config;
pub mod report;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use fedvla_aggregator::records::read_metrics;
use fedvla_aggregator::run_dir::write_atomic;

pub use self::config::{Judge, Range, Trial, TuneConfig};
use self::report::{Judged, RungResult, TrialRecord, TuneReport};
use crate::experiment::report::{REPORT_JSON, Report};
use crate::experiment::runner::{OnStart, RunSpec, execute};
use crate::experiment::{self, Arm, ExperimentConfig, Mode, last_heldout};

/// The search's configuration as it started, which a resumed search must equal.
pub const SEARCH_FILE: &str = "search.toml";
/// The winner, as a whole run configuration.
pub const BEST_CONFIG: &str = "best.toml";
/// The experiment that judges the search afresh, in the search's folder.
pub const JUDGE: &str = "judge";
/// The judged arms: the base, and the best configuration the search drew.
pub const BASE_ARM: &str = "base";
pub const DRAWN_ARM: &str = "best-drawn";

/// Runs the search (what has not finished yet), writes `best.toml`, judges the best drawn finalist against the base,
/// and writes the report. Returns the search's folder.
pub fn run(config: &TuneConfig, on_start: OnStart<'_>) -> anyhow::Result<PathBuf> {
    let dir = config.dir();
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    pin(config, &dir)?;
    let trials = config.sample();
    let mut results: BTreeMap<usize, Vec<RungResult>> = BTreeMap::new();
    let mut alive: Vec<&Trial> = trials.iter().collect();
    for (rung, &rounds) in config.rungs.iter().enumerate() {
        println!("rung {} of {}: {} trials of {rounds} rounds", rung + 1, config.rungs.len(), alive.len());
        let runs = alive
            .iter()
            .map(|trial| {
                Ok(RunSpec {
                    label: format!("trial {} at {rounds} rounds", trial.id),
                    path: config.trial_path(trial, rounds),
                    mode: Mode::Federated,
                    config: config.trial_config(trial, rounds)?,
                    final_sim: None,
                })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let finals = execute(&runs, config.parallel_trials, on_start)?;
        for ((trial, run), evaluation) in alive.iter().zip(&runs).zip(&finals) {
            let heldout_loss = last_heldout(&read_metrics(&run.path)?).map(|e| e.heldout_loss);
            let result = RungResult { rounds, heldout_loss, train_seconds: evaluation.train_seconds };
            results.entry(trial.id).or_default().push(result);
        }
        let at_this_rung = |trial: &Trial| results.get(&trial.id).and_then(|r| r.last());
        alive.sort_by(|a, b| by_loss(at_this_rung(a), at_this_rung(b)).then(a.id.cmp(&b.id)));
        if rung + 1 < config.rungs.len() {
            alive.truncate((alive.len() / config.reduction).max(1));
            if !alive.iter().any(|trial| trial.id == 0) {
                alive.push(&trials[0]);
            }
            let ids: Vec<String> = alive.iter().map(|t| t.id.to_string()).collect();
            println!("on to the next rung: trials {}", ids.join(", "));
        }
    }
    let best = alive.first().copied().context("no trial ran")?;
    let drawn = alive.iter().copied().find(|trial| trial.id != 0);
    write_best(config, best, results.get(&best.id).and_then(|r| r.last()?.heldout_loss))?;
    let mut records = trial_records(config, &trials, &results);
    records.sort_by(|a, b| {
        b.rungs.len().cmp(&a.rungs.len()).then(by_loss(a.rungs.last(), b.rungs.last())).then(a.trial.cmp(&b.trial))
    });
    let mut tune_report = TuneReport {
        name: config.name.clone(),
        search_seed: config.search_seed,
        rungs: config.rungs.clone(),
        reduction: config.reduction,
        trials: records,
        best: best.id,
        judged: None,
    };
    // The search's table stands before the judged runs start: they take as long as the search's last rung again.
    report::write(&tune_report, config)?;
    match (best.id, drawn) {
        (0, Some(drawn)) => println!(
            "best: the base configuration (no drawn trial beat it at the full budget); judging the best drawn, trial \
             {} ({}), against it afresh",
            drawn.id,
            drawn.overrides(&config.space)
        ),
        (0, None) => println!("best: the base configuration; judging it afresh"),
        (id, _) => println!("best: trial {id} ({}); judging it afresh against the base", best.overrides(&config.space)),
    }
    let judge = judge_experiment(config, drawn, &dir);
    let judge_dir = experiment::run(&judge, on_start)?;
    let text = std::fs::read(judge_dir.join(REPORT_JSON)).context("reading the judged runs' report")?;
    let judged_report: Report = serde_json::from_slice(&text).context("parsing the judged runs' report")?;
    tune_report.judged = Some(Judged {
        report: judged_report,
        drawn: drawn.map(|trial| trial.id),
        drawn_minus_base: report::paired_difference(&judge, BASE_ARM, DRAWN_ARM)?,
    });
    report::write(&tune_report, config)?;
    Ok(dir)
}

/// Lower held-out loss first; a rung without one last.
fn by_loss(a: Option<&RungResult>, b: Option<&RungResult>) -> std::cmp::Ordering {
    let loss = |r: Option<&RungResult>| r.and_then(|r| r.heldout_loss).unwrap_or(f64::INFINITY);
    loss(a).total_cmp(&loss(b))
}

/// Keeps the search's configuration beside its runs, and refuses to resume a search of another: its runs would be
/// read back as if they were this one's.
fn pin(config: &TuneConfig, dir: &Path) -> anyhow::Result<()> {
    let path = dir.join(SEARCH_FILE);
    // How many trials run at once changes no result.
    let pinned = TuneConfig { parallel_trials: 1, ..config.clone() };
    if path.exists() {
        let text = std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
        let started: TuneConfig = toml::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        anyhow::ensure!(
            started == pinned,
            "{} holds a search started with another configuration ({}): give this one another name or output-dir",
            dir.display(),
            path.display()
        );
        return Ok(());
    }
    let text = toml::to_string(&pinned).context("serializing the search's configuration")?;
    write_atomic(&path, text.as_bytes())?;
    Ok(())
}

/// `best.toml`: the winner's whole run configuration, at the base's budget, with a header saying where it comes
/// from.
fn write_best(config: &TuneConfig, best: &Trial, loss: Option<f64>) -> anyhow::Result<()> {
    let run_config = config.full_config(best)?;
    let path = config.dir().join(BEST_CONFIG);
    let overrides = best.overrides(&config.space);
    let header = format!(
        "# The best configuration of the search `{}` (trial {}, held-out loss {} after {} rounds): the base\n\
         # configuration ({}) with `{}`.\n# Run it: fedvla simulate --config {}\n\n",
        config.name,
        best.id,
        loss.map_or("none".to_owned(), |l| format!("{l:.4}")),
        run_config.num_server_rounds,
        if config.run_config.is_empty() { "configs/default.toml" } else { &config.run_config },
        if overrides.is_empty() { "nothing changed" } else { &overrides },
        path.display()
    );
    write_atomic(&path, format!("{header}{}", run_config.to_toml()).as_bytes())?;
    Ok(())
}

fn trial_records(
    config: &TuneConfig,
    trials: &[Trial],
    results: &BTreeMap<usize, Vec<RungResult>>,
) -> Vec<TrialRecord> {
    let top = config.rungs.last().copied();
    trials
        .iter()
        .map(|trial| {
            let rungs = results.get(&trial.id).cloned().unwrap_or_default();
            let last = rungs.last().map(|r| r.rounds);
            TrialRecord {
                trial: trial.id,
                params: trial.params.clone(),
                overrides: trial.overrides(&config.space),
                stopped_after: last.filter(|&rounds| Some(rounds) != top),
                rungs,
            }
        })
        .collect()
}

/// The experiment that judges the search afresh: the base and the best drawn finalist (none where no drawn trial
/// reached the last rung) on the judge's seeds, with its overrides (the data), final sim evaluations on its layouts.
pub fn judge_experiment(config: &TuneConfig, drawn: Option<&Trial>, dir: &Path) -> ExperimentConfig {
    let mut arms = vec![Arm { name: BASE_ARM.into(), mode: Mode::Federated, run_config: String::new() }];
    if let Some(drawn) = drawn {
        arms.push(Arm { name: DRAWN_ARM.into(), mode: Mode::Federated, run_config: drawn.overrides(&config.space) });
    }
    ExperimentConfig {
        name: JUDGE.into(),
        seeds: config.judge.seeds.clone(),
        eval_episodes: config.judge.eval_episodes,
        eval_seed: config.judge.eval_seed,
        run_config: format!("{} {}", config.run_config, config.judge.run_config).trim().to_owned(),
        output_dir: dir.display().to_string(),
        parallel_runs: config.parallel_trials,
        arms,
    }
}
