//! A tiny search end to end (the tiny SmolVLA, 4 trials, rungs of 1 and 2 rounds): successive halving stops half
//! the trials (the base goes on whatever its first rung), the winner's best.toml is a run configuration `simulate
//! --config` takes as it is (and run so, ends as its trial did), the best drawn finalist and the base are judged
//! afresh on another dataset and other seeds with intervals, a search killed in a run resumes by running that run
//! alone, and the same search seed gives the same table (run 2 at a time or 1).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::read_metrics;
use fedvla_aggregator::run_dir::RunDir;
use fedvla_server::experiment::{FINAL_FILE, last_heldout};
use fedvla_server::runs::{self, Bars};
use fedvla_server::tune::report::{REPORT_JSON, REPORT_MD, TRIALS_PLOT, TuneReport};
use fedvla_server::tune::{self, BEST_CONFIG, Judge, Range, TuneConfig};
use fedvla_workloads::datagen::{GenDataOptions, generate_dataset};

fn config(out: &Path, search_data: &Path, judge_data: &Path, parallel_trials: usize) -> TuneConfig {
    let run_config = format!(
        "model-size=tiny dataset={} num-clients=2 min-clients=2 min-fit=2 num-server-rounds=2 local-steps=2 \
         batch-size=2 rollout-episodes=1 client-rollout-episodes=0 rollout-max-frames=30 eval-every=2",
        search_data.display()
    );
    let space = BTreeMap::from([
        ("lr".to_owned(), Range::LogUniform([1e-4, 3e-2])),
        ("strategy".to_owned(), Range::Choice(vec!["fedavg".into(), "fedavgm".into()])),
        (
            "steps".to_owned(),
            Range::Joint(vec!["local-steps=2 batch-size=2".into(), "local-steps=1 batch-size=4".into()]),
        ),
    ]);
    TuneConfig {
        name: "tiny".into(),
        run_config,
        search_seed: 11,
        trials: 4,
        rungs: vec![1, 2],
        reduction: 2,
        parallel_trials,
        output_dir: out.display().to_string(),
        space,
        judge: Judge {
            seeds: vec![5, 6],
            run_config: format!("dataset={}", judge_data.display()),
            eval_episodes: 2,
            eval_seed: 10_000,
        },
    }
}

fn read_report(dir: &Path) -> TuneReport {
    serde_json::from_slice(&std::fs::read(dir.join(REPORT_JSON)).unwrap()).unwrap()
}

/// The trials' table without its wall-clock figures, which no two runs share.
fn table(report: &TuneReport) -> serde_json::Value {
    let mut json = serde_json::to_value(&report.trials).unwrap();
    for trial in json.as_array_mut().unwrap() {
        for rung in trial["rungs"].as_array_mut().unwrap() {
            rung.as_object_mut().unwrap().remove("train_seconds");
        }
    }
    json
}

#[test]
fn a_tiny_search_stops_trials_early_judges_its_winner_afresh_resumes_and_repeats_itself() {
    let tmp = tempfile::tempdir().unwrap();
    let search_data = tmp.path().join("search-data");
    let judge_data = tmp.path().join("judge-data");
    for (path, seed) in [(&search_data, 0), (&judge_data, 1_000)] {
        let options = GenDataOptions { episodes: 6, seed, image_size: 32, ..Default::default() };
        generate_dataset(path, &options, |_| {}).unwrap();
    }
    let first = config(&tmp.path().join("a"), &search_data, &judge_data, 1);
    first.check().unwrap();
    let dir = tune::run(&first, &|_| Ok(())).unwrap();
    let report = read_report(&dir);

    // Successive halving: 4 trials at 1 round, the best 2 of them on to 2 rounds, and the base (trial 0) with them
    // wherever it was not among them; the others stopped after 1.
    assert_eq!(report.trials.len(), 4);
    let at_1 = |t: &tune::report::TrialRecord| t.rungs[0].heldout_loss.unwrap();
    let mut by_first_rung: Vec<_> = report.trials.iter().collect();
    by_first_rung.sort_by(|a, b| at_1(a).total_cmp(&at_1(b)).then(a.trial.cmp(&b.trial)));
    let mut went_on: Vec<usize> = by_first_rung[..2].iter().map(|t| t.trial).collect();
    if !went_on.contains(&0) {
        went_on.push(0);
    }
    let stopped: Vec<_> = report.trials.iter().filter(|t| t.stopped_after == Some(1)).collect();
    assert_eq!(stopped.len(), 4 - went_on.len(), "{:#?}", report.trials);
    assert!(stopped.iter().all(|t| t.rungs.len() == 1 && !went_on.contains(&t.trial)));
    let finalists: Vec<_> = report.trials.iter().filter(|t| t.stopped_after.is_none()).collect();
    assert!(finalists.iter().all(|t| t.rungs.len() == 2 && went_on.contains(&t.trial)), "{:#?}", report.trials);
    assert_eq!(finalists.len(), went_on.len());
    // The winner is the best finalist, the finalists best first.
    assert_eq!(report.best, finalists[0].trial);
    assert!(finalists.windows(2).all(|w| w[0].last_loss().unwrap() <= w[1].last_loss().unwrap()));
    // Trial 0 is the base configuration; the others drew every key of the space.
    let base = report.trials.iter().find(|t| t.trial == 0).unwrap();
    assert!(base.params.is_empty() && base.overrides.is_empty());
    for trial in report.trials.iter().filter(|t| t.trial != 0) {
        assert_eq!(trial.params.keys().collect::<Vec<_>>(), ["lr", "steps", "strategy"]);
    }
    // Every trial ran on the search's data and seed, without sim rollouts, for its rung's rounds.
    let trial_run = dir.join(format!("trials/trial_{:03}/rounds_2", report.best));
    let run = RunConfig::load(&trial_run.join("config.toml")).unwrap();
    assert_eq!((run.num_server_rounds, run.seed, run.rollout_episodes), (2, 0, 0));
    assert_eq!(run.dataset, search_data.display().to_string());

    // best.toml: the winner whole, as `simulate --config` reads it (RunConfig::load), at the base's budget.
    let best_trial = report.trials.iter().find(|t| t.trial == report.best).unwrap();
    let best = RunConfig::load(&dir.join(BEST_CONFIG)).unwrap();
    let expected = first.base().unwrap().with_overrides(&best_trial.overrides).unwrap();
    assert_eq!(best, expected);
    assert_eq!((best.num_server_rounds, best.rollout_episodes, best.eval_every), (2, 1, 2));
    // ... and run so, it is the winner's last trial again: the same held-out loss.
    let rerun = tmp.path().join("best-run");
    runs::federated(best.clone(), RunDir::create_at(&rerun, &best).unwrap(), &Bars::hidden()).unwrap();
    assert_eq!(last_heldout(&read_metrics(&rerun).unwrap()).map(|e| e.heldout_loss), best_trial.last_loss());

    // Judged afresh: the base and the best drawn finalist (the winner, or the runner-up where the base won) on the
    // judge's seeds and dataset, with intervals and the paired difference.
    let judged = report.judged.as_ref().expect("the search judges what it found");
    let arms: Vec<&str> = judged.report.arms.iter().map(|a| a.name.as_str()).collect();
    assert_eq!(arms, ["base", "best-drawn"]);
    assert_eq!(judged.drawn, finalists.iter().map(|t| t.trial).find(|&t| t != 0));
    assert!(judged.drawn_minus_base.is_some());
    for arm in &judged.report.arms {
        assert_eq!(arm.seeds, [5, 6]);
        assert_eq!(arm.episodes, 4, "2 seeds x 2 final episodes");
        for i in [arm.final_.heldout_loss, arm.final_.success_rate, arm.success_pooled] {
            assert!(i.ci95_low <= i.mean && i.mean <= i.ci95_high, "{}: {i:?}", arm.name);
        }
        let judged_run = RunConfig::load(&dir.join(format!("judge/{}/seed_5/config.toml", arm.name))).unwrap();
        assert_eq!(judged_run.dataset, judge_data.display().to_string(), "data the search never saw");
    }
    let markdown = std::fs::read_to_string(dir.join(REPORT_MD)).unwrap();
    assert!(markdown.contains("| rank | trial | lr | steps | strategy |"), "{markdown}");
    assert!(markdown.contains("## Judged afresh"), "{markdown}");
    let png = image::open(dir.join(TRIALS_PLOT)).unwrap().to_luma8();
    let mean = png.pixels().map(|p| f64::from(p.0[0])).sum::<f64>() / png.len() as f64;
    let var = png.pixels().map(|p| (f64::from(p.0[0]) - mean).powi(2)).sum::<f64>() / png.len() as f64;
    assert!(var > 50.0, "{TRIALS_PLOT} is not blank");

    // Killed in the winner's last run: started again, the search runs that run alone and ends where it did.
    std::fs::remove_file(trial_run.join(FINAL_FILE)).unwrap();
    let started: Mutex<Vec<PathBuf>> = Mutex::new(Vec::new());
    tune::run(&first, &|run| {
        started.lock().unwrap().push(run.to_owned());
        Ok(())
    })
    .unwrap();
    assert_eq!(started.into_inner().unwrap(), [trial_run]);
    let resumed = read_report(&dir);
    assert_eq!(table(&resumed), table(&report));
    assert_eq!(resumed.judged.as_ref().unwrap().report, judged.report);

    // The same search seed, 2 trials at a time: the same table.
    let second = config(&tmp.path().join("b"), &search_data, &judge_data, 2);
    let again = read_report(&tune::run(&second, &|_| Ok(())).unwrap());
    assert_eq!(table(&again), table(&report), "same seed, same table");
    assert_eq!(again.best, report.best);

    // Another search in the first one's folder is refused: its runs are not this one's.
    let other = TuneConfig { search_seed: 12, ..first.clone() };
    let err = tune::run(&other, &|_| Ok(())).expect_err("a search of another configuration");
    assert!(format!("{err:#}").contains("another configuration"), "{err:#}");
}

#[test]
fn a_search_that_would_not_judge_fairly_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let (data, other) = (tmp.path().join("data"), tmp.path().join("other"));
    let good = config(tmp.path(), &data, &other, 1);
    good.check().unwrap();
    let refused = |config: TuneConfig, expected: &str| {
        let err = config.check().expect_err(expected);
        assert!(format!("{err:#}").contains(expected), "{expected}: {err:#}");
    };
    refused(
        TuneConfig { judge: Judge { run_config: String::new(), ..good.judge.clone() }, ..good.clone() },
        "the search's dataset",
    );
    refused(
        TuneConfig { judge: Judge { seeds: vec![0, 1], ..good.judge.clone() }, ..good.clone() },
        "include the search's seed",
    );
    refused(TuneConfig { rungs: vec![1, 3], ..good.clone() }, "must be the base configuration's num-server-rounds");
    let mut space = good.space.clone();
    space.insert("seed".into(), Range::IntUniform([0, 9]));
    refused(TuneConfig { space, ..good.clone() }, "the search's own to set");
    let mut space = good.space.clone();
    space.insert("lr".into(), Range::LogUniform([0.0, 1e-3]));
    refused(TuneConfig { space, ..good.clone() }, "above 0");
    let mut space = good.space.clone();
    space.insert("local-steps".into(), Range::LogUniform([1.0, 4.0]));
    refused(TuneConfig { space, ..good.clone() }, "is not of type integer");
    refused(
        TuneConfig { judge: Judge { run_config: "lr=0.1 dataset=x".into(), ..good.judge.clone() }, ..good },
        "which the search sets",
    );
}

#[test]
fn shipped_searches_load_and_judge_on_data_and_layouts_they_never_saw() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/tune");
    let mut shipped = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let config = TuneConfig::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        assert!(config.judge.seeds.len() >= 3, "{}: the issue asks for 3 seeds", path.display());
        assert!(config.judge.eval_episodes >= 50, "{}", path.display());
        let base = config.base().unwrap();
        let judged = base.with_overrides(&config.judge.run_config).unwrap();
        // The embedded dataset records from its dataset-seed on, never more than twice its episodes.
        let recorded = |run: &RunConfig| run.dataset_seed..run.dataset_seed + 2 * run.dataset_episodes as u64;
        let apart = |a: std::ops::Range<u64>, b: std::ops::Range<u64>| a.end <= b.start || b.end <= a.start;
        let layouts = config.judge.eval_seed..config.judge.eval_seed + config.judge.eval_episodes as u64;
        for run in [&base, &judged] {
            assert!(apart(layouts.clone(), recorded(run)), "{}: layouts recorded", path.display());
        }
        assert!(apart(recorded(&base), recorded(&judged)), "{}: the judged data overlaps the search's", path.display());
        shipped += 1;
    }
    assert!(shipped >= 1, "configs/tune/federation.toml is shipped");
}
