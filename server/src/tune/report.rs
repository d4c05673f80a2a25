//! A search's report: `report.json` ([`TuneReport`]: every trial's held-out loss at each rung it ran, the winner,
//! and once judged, the judged runs' report with the best drawn finalist's paired difference from the base),
//! `report.md` (its tables) and `trials.png` (each trial's held-out loss over the rungs).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use anyhow::Context;
use fedvla_aggregator::records::read_metrics;
use fedvla_aggregator::run_dir::write_atomic;
use serde::{Deserialize, Serialize};

use super::config::{TuneConfig, value_text};
use crate::experiment::plot::{Line, plot_log_lines};
use crate::experiment::report::{Report, interval, optional_interval};
use crate::experiment::stats::Interval;
use crate::experiment::{ExperimentConfig, last_heldout, read_final};

pub const REPORT_JSON: &str = "report.json";
pub const REPORT_MD: &str = "report.md";
pub const TRIALS_PLOT: &str = "trials.png";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TuneReport {
    pub name: String,
    pub search_seed: u64,
    /// The rungs' budgets, rounds.
    pub rungs: Vec<u64>,
    pub reduction: usize,
    /// Every trial, the best first: by the last rung it reached, then its held-out loss there.
    pub trials: Vec<TrialRecord>,
    /// The winner's trial number (0: the base configuration won).
    pub best: usize,
    /// Once judged: the base and the best drawn finalist on seeds, data and layouts the search never used.
    pub judged: Option<Judged>,
}

/// One configuration of the search and how far it went.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrialRecord {
    pub trial: usize,
    /// The value drawn for each key of the space (none: the base configuration).
    pub params: BTreeMap<String, toml::Value>,
    /// The same as `--run-config` overrides on the base.
    pub overrides: String,
    /// Each rung the trial ran, in order.
    pub rungs: Vec<RungResult>,
    /// The rounds after which successive halving stopped it; `None`: it ran the last rung.
    pub stopped_after: Option<u64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct RungResult {
    pub rounds: u64,
    /// The server's held-out loss after the rung's last round (`None`: no round was evaluated; ranked last).
    pub heldout_loss: Option<f64>,
    pub train_seconds: f64,
}

impl TrialRecord {
    /// The held-out loss at the last rung the trial ran.
    pub fn last_loss(&self) -> Option<f64> {
        self.rungs.last().and_then(|r| r.heldout_loss)
    }
}

/// The judged runs (`judge/`, an experiment of the base and the best configuration the search drew).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Judged {
    pub report: Report,
    /// The trial judged against the base: the best drawn finalist (the winner, or where the base won, the
    /// runner-up); none where no drawn trial reached the last rung.
    pub drawn: Option<usize>,
    /// That trial minus the base, paired by seed.
    pub drawn_minus_base: Option<PairedDifference>,
}

/// A difference of figures between two arms run on the same seeds: the mean and Student-t 95% interval of the
/// per-seed differences.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PairedDifference {
    pub heldout_loss: Interval,
    pub success_rate: Interval,
}

/// The per-seed differences `arm - base` of the judged experiment's runs.
pub fn paired_difference(judge: &ExperimentConfig, base: &str, arm: &str) -> anyhow::Result<Option<PairedDifference>> {
    let (Some(base), Some(arm)) =
        (judge.arms.iter().find(|a| a.name == base), judge.arms.iter().find(|a| a.name == arm))
    else {
        return Ok(None);
    };
    let figures = |run: &Path| -> anyhow::Result<(f64, f64)> {
        let metrics = read_metrics(run)?;
        let loss = last_heldout(&metrics).with_context(|| format!("{}: no evaluated round", run.display()))?;
        let sim = read_final(run)?.sim.with_context(|| format!("{}: no final sim evaluation", run.display()))?;
        Ok((loss.heldout_loss, sim.success_rate.unwrap_or(0.0)))
    };
    let mut losses = Vec::new();
    let mut successes = Vec::new();
    for &seed in &judge.seeds {
        let (base_loss, base_success) = figures(&judge.run_path(base, seed))?;
        let (loss, success) = figures(&judge.run_path(arm, seed))?;
        losses.push(loss - base_loss);
        successes.push(success - base_success);
    }
    Ok(Interval::t(&losses)
        .zip(Interval::t(&successes))
        .map(|(heldout_loss, success_rate)| PairedDifference { heldout_loss, success_rate }))
}

/// Writes `report.json`, `report.md` and `trials.png` into the search's folder.
pub fn write(report: &TuneReport, config: &TuneConfig) -> anyhow::Result<()> {
    let dir = config.dir();
    let json = serde_json::to_vec_pretty(report).context("serializing the search's report")?;
    write_atomic(&dir.join(REPORT_JSON), &json)?;
    write_atomic(&dir.join(REPORT_MD), markdown(report, config).as_bytes())?;
    let lines: Vec<Line> = report
        .trials
        .iter()
        .map(|t| Line {
            label: match t.trial {
                0 => Some("trial 0 (base)".to_owned()),
                id if id == report.best => Some(format!("trial {id} (best)")),
                _ => None,
            },
            points: t.rungs.iter().filter_map(|r| Some((r.rounds, r.heldout_loss?))).collect(),
        })
        .collect();
    plot_log_lines(
        &dir.join(TRIALS_PLOT),
        "held-out loss of each trial at each rung it ran",
        "held-out loss (log scale)",
        &lines,
    )
}

fn markdown(report: &TuneReport, config: &TuneConfig) -> String {
    let mut md = String::new();
    let _ = writeln!(md, "# Search `{}`\n", report.name);
    let base = if config.run_config.is_empty() {
        "configs/default.toml".to_owned()
    } else {
        format!("`{}`", config.run_config)
    };
    let _ = writeln!(
        md,
        "{} trials: trial 0 the base configuration ({base}), the others drawn from the space below with search seed \
         {}. Successive halving over rungs of {:?} rounds: every trial is a federation of that many rounds on the same \
         data and run seed, judged on the server's held-out episodes (held-out loss after its last round, lower is \
         better); after each rung the best 1/{} go on, and the base with them (a short rung can rank it low where it \
         ends best). `-`: not run at that rung.\n",
        config.trials, report.search_seed, report.rungs, report.reduction
    );
    for (key, range) in &config.space {
        let _ = writeln!(md, "- `{key}`: {range}");
    }
    md.push('\n');
    let keys: Vec<&String> = config.space.keys().collect();
    // The base's own values, beside trial 0 (a joint choice's label is no key of it).
    let base_values = config.base().ok().and_then(|b| toml::Table::try_from(b).ok()).unwrap_or_default();
    let _ = write!(md, "| rank | trial |");
    for key in &keys {
        let _ = write!(md, " {key} |");
    }
    for rounds in &report.rungs {
        let _ = write!(md, " held-out loss at {rounds} |");
    }
    md.push_str(" train time (s) |\n|---|---|");
    md.push_str(&"---|".repeat(keys.len() + report.rungs.len() + 1));
    md.push('\n');
    for (rank, trial) in report.trials.iter().enumerate() {
        let _ = write!(md, "| {} | {} |", rank + 1, trial.trial);
        for key in &keys {
            let value = match trial.params.get(*key) {
                Some(value) => value_text(value),
                None => base_values.get(*key).map_or("base".to_owned(), |v| format!("{} (base)", value_text(v))),
            };
            let _ = write!(md, " {value} |");
        }
        for rounds in &report.rungs {
            let loss = trial.rungs.iter().find(|r| r.rounds == *rounds).map(|r| r.heldout_loss);
            let cell = match loss {
                Some(Some(loss)) => format!("{loss:.4}"),
                Some(None) => "not evaluated".to_owned(),
                None => "-".to_owned(),
            };
            let _ = write!(md, " {cell} |");
        }
        let seconds: f64 = trial.rungs.iter().map(|r| r.train_seconds).sum();
        let _ = writeln!(md, " {seconds:.0} |");
    }
    let best = report.trials.iter().find(|t| t.trial == report.best);
    let overrides = best.map_or(String::new(), |t| t.overrides.clone());
    let _ = writeln!(
        md,
        "\nBest: trial {} (`{}`), written whole to `best.toml`: `fedvla simulate --config {}` runs it. Plot: `{TRIALS_PLOT}`.",
        report.best,
        if overrides.is_empty() { "the base configuration" } else { &overrides },
        config.dir().join(super::BEST_CONFIG).display()
    );
    if let Some(judged) = &report.judged {
        judged_markdown(&mut md, judged, report.best, config);
    }
    md
}

fn judged_markdown(md: &mut String, judged: &Judged, best: usize, config: &TuneConfig) {
    let drawn = match judged.drawn {
        Some(id) => {
            let standing = if id == best { "the winner" } else { "which the base beat" };
            format!("the best configuration the search drew (`{}`: trial {id}, {standing})", super::DRAWN_ARM)
        }
        None => "no drawn configuration (none reached the last rung)".to_owned(),
    };
    let _ = writeln!(
        md,
        "\n## Judged afresh\n\nThe base and {drawn}, each on seeds {:?} (the search ran seed {}), with \
         `{}` (data the search never saw), their last models rolled out on {} sim layouts from seed {}. Mean and \
         Student-t 95% interval over seeds; pooled success with its Wilson interval. The full report: \
         `judge/report.md`.\n",
        config.judge.seeds,
        config.base().map_or(0, |b| b.seed),
        config.judge.run_config,
        config.judge.eval_episodes,
        config.judge.eval_seed
    );
    md.push_str(
        "| arm | held-out loss | action L1 | sim success | success, pooled (Wilson) |\n|---|---|---|---|---|\n",
    );
    for arm in &judged.report.arms {
        let f = &arm.final_;
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {} ({}/{}) |",
            arm.name,
            interval(&f.heldout_loss, 4),
            optional_interval(f.action_l1.as_ref(), 2),
            interval(&f.success_rate, 2),
            interval(&arm.success_pooled, 2),
            arm.successes,
            arm.episodes
        );
    }
    match &judged.drawn_minus_base {
        None => md.push_str("\nNo drawn configuration to judge against the base.\n"),
        Some(d) => {
            let verdict = |i: &Interval, lower_is_better: bool| match (i.ci95_high < 0.0, i.ci95_low > 0.0) {
                (true, _) if lower_is_better => "better",
                (_, true) if !lower_is_better => "better",
                (true, _) | (_, true) => "worse",
                _ => "no difference shown",
            };
            let _ = writeln!(
                md,
                "\nBest drawn minus base, paired by seed: held-out loss {} ({}), sim success {} ({}).",
                interval(&d.heldout_loss, 4),
                verdict(&d.heldout_loss, true),
                interval(&d.success_rate, 2),
                verdict(&d.success_rate, false)
            );
        }
    }
}
