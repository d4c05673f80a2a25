//! A tiny experiment end to end (2 arms x 2 seeds, the tiny SmolVLA, a few steps): every run, the final sim
//! evaluation, report.json's schema with intervals around their means, the plots, resuming a finished grid, and
//! the same numbers from a second experiment of the same seeds, run two at a time.

use std::path::Path;

use fedvla_server::experiment::report::{REPORT_JSON, Report};
use fedvla_server::experiment::{self, Arm, ExperimentConfig, Mode};
use fedvla_workloads::datagen::{GenDataOptions, generate_dataset};

fn config(out: &Path, dataset: &Path) -> ExperimentConfig {
    let run_config = format!(
        "model-size=tiny dataset={} num-clients=2 min-clients=2 min-fit=2 num-server-rounds=2 local-steps=2 \
         batch-size=2 rollout-episodes=1 client-rollout-episodes=0 rollout-max-frames=30",
        dataset.display()
    );
    ExperimentConfig {
        name: "tiny".into(),
        seeds: vec![3, 4],
        eval_episodes: 2,
        eval_seed: 10_000,
        run_config,
        output_dir: out.display().to_string(),
        parallel_runs: 1,
        arms: vec![
            Arm { name: "centralized".into(), mode: Mode::Centralized, run_config: String::new() },
            // Client-level DP (noise 0.3 x 0.05 / 2 clients per value): the report states the privacy each round spent.
            Arm {
                name: "dp-fedavg".into(),
                mode: Mode::Federated,
                run_config: "dp-noise-multiplier=0.3 dp-clip-norm=0.05".into(),
            },
        ],
    }
}

/// The report without its wall-clock figures, which no two runs share.
fn numbers(report: &Report) -> serde_json::Value {
    let mut json = serde_json::to_value(report).unwrap();
    for arm in json["arms"].as_array_mut().unwrap() {
        arm.as_object_mut().unwrap().remove("train_seconds");
    }
    json
}

#[test]
fn a_tiny_experiment_reports_intervals_and_repeats_itself() {
    let tmp = tempfile::tempdir().unwrap();
    let dataset = tmp.path().join("data");
    generate_dataset(&dataset, &GenDataOptions { episodes: 6, seed: 0, image_size: 32, ..Default::default() }, |_| {})
        .unwrap();
    let first = config(&tmp.path().join("a"), &dataset);
    let dir = experiment::run(&first, &|_| Ok(())).unwrap();
    let report: Report = serde_json::from_slice(&std::fs::read(dir.join(REPORT_JSON)).unwrap()).unwrap();
    assert_eq!(report.arms.iter().map(|a| a.name.as_str()).collect::<Vec<_>>(), ["centralized", "dp-fedavg"]);
    for arm in &report.arms {
        assert_eq!(arm.seeds, [3, 4]);
        let f = &arm.final_;
        for i in [Some(f.heldout_loss), f.action_mse, f.action_l1, Some(f.success_rate), Some(arm.success_pooled)] {
            let i = i.expect("every figure is reported");
            assert!(i.ci95_low <= i.mean && i.mean <= i.ci95_high, "{}: {i:?}", arm.name);
        }
        assert_eq!(arm.episodes, 4, "2 seeds x 2 final episodes");
    }
    assert!(report.arms[0].ratio_to_centralized.is_none());
    assert!(report.arms[1].ratio_to_centralized.is_some());
    // Epsilon (at the run's delta) after every round, growing with the rounds; none for the arm without DP.
    assert!(report.arms[0].privacy.is_none());
    let privacy = report.arms[1].privacy.as_ref().expect("the DP arm reports its privacy");
    assert_eq!(privacy.noise_multiplier, 0.3);
    assert_eq!(privacy.epsilon_per_round.iter().map(|e| e.round).collect::<Vec<_>>(), [1, 2]);
    let [one, two] = [0, 1].map(|i| privacy.epsilon_per_round[i].epsilon);
    assert!(0.0 < one && one < two && two.is_finite(), "{one} {two}");
    let markdown = std::fs::read_to_string(dir.join(experiment::report::REPORT_MD)).unwrap();
    assert!(markdown.contains("Privacy spent") && markdown.contains(&format!("{two:.3}")), "{markdown}");
    // The schema the issue names, read by key.
    let raw: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join(REPORT_JSON)).unwrap()).unwrap();
    for key in ["heldout_loss", "action_mse", "action_l1", "success_rate"] {
        for bound in ["mean", "ci95_low", "ci95_high"] {
            assert!(raw["arms"][1]["final"][key][bound].is_number(), "final.{key}.{bound}");
        }
    }
    for plot in ["heldout_loss.png", "success_rate.png"] {
        let png = image::open(dir.join(plot)).unwrap().to_luma8();
        let mean = png.pixels().map(|p| f64::from(p.0[0])).sum::<f64>() / png.len() as f64;
        let var = png.pixels().map(|p| (f64::from(p.0[0]) - mean).powi(2)).sum::<f64>() / png.len() as f64;
        assert!(var > 50.0, "{plot} is not blank");
    }
    // A finished run keeps its models and metrics, not its clients' copies of the dataset.
    let run = tmp.path().join("a/tiny/dp-fedavg/seed_4");
    assert!(run.join("metrics.jsonl").is_file() && run.join("global_model").is_dir());
    assert!(!run.join("shards").exists(), "a finished run's shards are removed");
    // Resumed, a finished grid runs nothing again: the runs' final evaluations stay as they were.
    let final_of = |root: &Path| std::fs::read(root.join("tiny/dp-fedavg/seed_4/final.json")).unwrap();
    let before = final_of(&tmp.path().join("a"));
    experiment::run(&first, &|_| panic!("no run should start")).unwrap();
    assert_eq!(final_of(&tmp.path().join("a")), before);

    // Two runs at a time: the same numbers.
    let second = ExperimentConfig { parallel_runs: 2, ..config(&tmp.path().join("b"), &dataset) };
    let again: Report = serde_json::from_slice(
        &std::fs::read(experiment::run(&second, &|_| Ok(())).unwrap().join(REPORT_JSON)).unwrap(),
    )
    .unwrap();
    assert_eq!(numbers(&again), numbers(&report), "same seeds, same numbers");

    // Layouts the dataset recorded are no held-out evaluation: the run is refused before it is scored.
    let on_training_layouts = ExperimentConfig {
        seeds: vec![3],
        eval_seed: 0,
        arms: first.arms[..1].to_vec(),
        ..config(&tmp.path().join("c"), &dataset)
    };
    let err = experiment::run(&on_training_layouts, &|_| Ok(())).expect_err("evaluation seeds recorded");
    assert!(format!("{err:#}").contains("a layout the training dataset"), "{err:#}");
}

#[test]
fn shipped_experiments_load_and_evaluate_on_unrecorded_layouts() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/experiments");
    let mut shipped = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        let config = ExperimentConfig::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        assert!(config.eval_episodes >= 50, "{}: the issue asks for at least 50 episodes per run", path.display());
        for arm in &config.arms {
            let run = config.run_config(arm, config.seeds[0]).unwrap();
            // The embedded dataset records seeds from 0 on, never as many as the evaluation's first seed.
            assert!(run.dataset_episodes * 2 < config.eval_seed as usize, "{}: {}", path.display(), arm.name);
        }
        shipped += 1;
    }
    assert!(shipped >= 1, "configs/experiments/fed-vs-central.toml is shipped");
}
