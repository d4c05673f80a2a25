//! Evaluation in the sim: the scripted expert's success rate on the evaluation seeds (the
//! acceptance bar for the sim and the success check), on every task too, a tiny random policy through
//! `fedvla eval`, a video that cannot be written costing no results, and the task names `fedvla tasks`
//! lists, which `eval --task` takes and refuses others than.

use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Output};

use fedvla_data::DirFiles;
use fedvla_data::video::{FrameSource, Mp4Frames, VideoFile};
use fedvla_policy::policy_dir::{Backbone, export};
use fedvla_policy::{FeatureStats, NormStats, SmolVlaConfig, WordTokenizer};
use fedvla_sim::TaskKind;
use fedvla_workloads::sim_eval::{
    Agent, DEFAULT_MAX_FRAMES, DEFAULT_SEED, RESULTS_FILE, SimEvalOptions, evaluate_in_sim, video_path,
};
use serde_json::Value;

fn fedvla(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_fedvla")).args(args).output().expect("fedvla runs")
}

fn results(out: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(out.join(RESULTS_FILE)).unwrap()).unwrap()
}

#[test]
fn expert_succeeds_on_at_least_90_percent_of_24_eval_seeds() {
    let out = tempfile::tempdir().unwrap();
    let opts = SimEvalOptions { episodes: 24, seed: DEFAULT_SEED, max_frames: DEFAULT_MAX_FRAMES, video_size: None };
    let mut reported = Vec::new();
    let expert = Agent::Expert { task: TaskKind::CubeInBowl };
    let summary = evaluate_in_sim(expert, &opts, out.path(), |i, r| reported.push((i, r.seed))).unwrap();

    let failed: Vec<u64> = summary.episodes.iter().filter(|e| !e.success).map(|e| e.seed).collect();
    let success_rate = summary.success_rate.unwrap();
    assert!(success_rate >= 0.9, "success rate {success_rate}; failed seeds {failed:?}");
    let expected: Vec<(usize, u64)> = (0..24).map(|i| (i, DEFAULT_SEED + i as u64)).collect();
    assert_eq!(reported, expected);
    assert!(!video_path(out.path(), 0).exists(), "video_size None films nothing");

    let json = results(out.path());
    assert_eq!(json["policy"], "expert");
    assert_eq!(json["episodes"].as_array().unwrap().len(), 24);
    assert_eq!(json["episodes"][3]["seed"], DEFAULT_SEED + 3);
    assert_eq!(json["success_rate"], success_rate);
    // Successful episodes end when the cube is in the bowl, well inside the budget.
    for e in summary.episodes.iter().filter(|e| e.success) {
        assert!((e.length as usize) < DEFAULT_MAX_FRAMES, "seed {} took {} frames", e.seed, e.length);
    }
    println!("expert: {:.1}% of 24 eval seeds, mean length {:?}", success_rate * 100.0, summary.mean_length);
}

#[test]
fn tiny_random_policy_is_rolled_out_filmed_and_reported() {
    let tmp = tempfile::tempdir().unwrap();
    let policy = tmp.path().join("policy");
    let cfg = SmolVlaConfig::tiny();
    let weights = fedvla_policy::weights::init_random(&cfg.param_specs(), 0);
    let six = |mean: f32, std: f32| FeatureStats { mean: vec![mean; 6], std: vec![std; 6] };
    let stats = NormStats {
        features: BTreeMap::from([
            ("observation.state".to_string(), six(0.0, 30.0)),
            ("action".to_string(), six(0.0, 30.0)),
        ]),
    };
    let tokenizer = WordTokenizer::from_texts([fedvla_sim::TASK]);
    export(
        &policy,
        &cfg,
        fedvla_policy::weights::host_refs(&weights),
        &stats,
        Backbone::Generated(&tokenizer),
        fedvla_policy::StoredDtype::F32,
    )
    .unwrap();

    let out = tmp.path().join("eval");
    let run = fedvla(&[
        "eval",
        "--policy",
        policy.to_str().unwrap(),
        "--episodes",
        "1",
        "--max-frames",
        "60",
        "--video-size",
        "64",
        "--out",
        out.to_str().unwrap(),
    ]);
    let stdout = String::from_utf8_lossy(&run.stdout);
    assert!(run.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&run.stderr));
    println!("{stdout}");

    let json = results(&out);
    assert_eq!(json["policy"], policy.to_str().unwrap());
    let episodes = json["episodes"].as_array().unwrap();
    assert_eq!(episodes.len(), 1);
    assert_eq!(episodes[0]["seed"], DEFAULT_SEED);
    let length = episodes[0]["length"].as_u64().unwrap();
    assert!((1..=60).contains(&length), "length {length}");
    assert!(json.get("video_errors").is_none(), "{json}");

    let video = std::fs::read(video_path(&out, 0)).unwrap();
    assert_eq!(&video[4..8], b"ftyp");
    assert!(video.windows(4).any(|w| w == b"moov"), "finished mp4 has its index");
    // 61 frames of 128x64 (the first before any action): far more than the boxes alone.
    assert!(video.len() > 4096, "{} bytes", video.len());
    let (dir, file) = (out.as_path(), video_path(&out, 0).strip_prefix(&out).unwrap().to_path_buf());
    let files = std::sync::Arc::new(DirFiles::new(dir));
    let decoded = VideoFile::open(&*files, &file).unwrap();
    assert_eq!(decoded.frame_count() as u64, length + 1, "the start and every step");
    let first = &Mp4Frames::new(files).frames_at(&file, &[0.0], 1e-3).unwrap()[0];
    assert_eq!((first.width, first.height), (128, 64), "top and wrist side by side");
    let half = |x0: usize| -> Vec<u8> {
        first.data.chunks_exact(128 * 3).flat_map(|row| row[x0 * 3..(x0 + 64) * 3].to_vec()).collect()
    };
    let (left, right) = (half(0), half(64));
    let diff = left.iter().zip(&right).map(|(a, b)| u64::from(a.abs_diff(*b))).sum::<u64>() / left.len() as u64;
    assert!(diff > 5, "the two cameras see different things (mean abs diff {diff})");
}

#[test]
fn a_video_that_cannot_be_written_keeps_every_result_and_fails_the_command() {
    let out = tempfile::tempdir().unwrap();
    // A directory where episode 0's video should go: creating the file fails.
    std::fs::create_dir(video_path(out.path(), 0)).unwrap();
    let run = fedvla(&[
        "eval",
        "--expert",
        "--episodes",
        "2",
        "--max-frames",
        "20",
        "--video-size",
        "32",
        "--out",
        out.path().to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success(), "{}", String::from_utf8_lossy(&run.stdout));
    assert!(stderr.contains("episode 0"), "{stderr}");

    let json = results(out.path());
    assert_eq!(json["episodes"].as_array().unwrap().len(), 2);
    assert_eq!(json["video_errors"].as_array().unwrap().len(), 1);
    assert_eq!(json["video_errors"][0]["episode"], 0);
    let second = std::fs::read(video_path(out.path(), 1)).unwrap();
    assert_eq!(&second[4..8], b"ftyp");
}

#[test]
fn expert_solves_every_task_on_at_least_90_percent_of_10_eval_seeds() {
    let out = tempfile::tempdir().unwrap();
    let opts = SimEvalOptions { episodes: 10, seed: DEFAULT_SEED, max_frames: DEFAULT_MAX_FRAMES, video_size: None };
    for task in TaskKind::ALL {
        let summary = evaluate_in_sim(Agent::Expert { task }, &opts, out.path(), |_, _| {}).unwrap();
        let failed: Vec<u64> = summary.episodes.iter().filter(|e| !e.success).map(|e| e.seed).collect();
        let success_rate = summary.success_rate.unwrap();
        assert!(success_rate >= 0.9, "{task}: success rate {success_rate}; failed seeds {failed:?}");
        println!("{task}: {:.0}% of 10 eval seeds, mean length {:?}", success_rate * 100.0, summary.mean_length);
    }
}

#[test]
fn tasks_are_listed_one_a_line_and_eval_takes_them_or_names_the_known_ones() {
    let listed = fedvla(&["tasks"]);
    assert!(listed.status.success());
    let names: Vec<&str> = TaskKind::ALL.iter().map(|task| task.name()).collect();
    assert_eq!(String::from_utf8_lossy(&listed.stdout).lines().collect::<Vec<_>>(), names);

    let out = tempfile::tempdir().unwrap();
    let eval = |task: &str| {
        let out = out.path().join(task);
        fedvla(&[
            "eval",
            "--expert",
            "--task",
            task,
            "--episodes",
            "1",
            "--video-size",
            "0",
            "--out",
            out.to_str().unwrap(),
        ])
    };
    let run = eval("stack");
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let json = results(&out.path().join("stack"));
    assert_eq!(json["policy"], "expert on stack");
    assert_eq!(json["episodes"][0]["seed"], DEFAULT_SEED);

    let run = eval("juggle");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("\"juggle\""), "{stderr}");
    for name in names {
        assert!(stderr.contains(name), "{stderr}");
    }
    // A policy takes tasks too (its rollouts cycle through them): the command line accepts them, and a policy
    // directory that is not there is refused by name.
    let run = fedvla(&["eval", "--policy", "p", "--task", "stack", "--episodes", "1", "--out", "never"]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("loading policy p"), "{stderr}");
}
