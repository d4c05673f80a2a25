//! A dataset laid out as `lerobot/svla_so100_pickplace` is (two cameras named `top` and `wrist` recording
//! 640x480, 30 fps, 6-d state and action named after the SO-100's joints, several tasks) runs as the README's
//! "Real SO-100 data" section says: `fedvla simulate` reads it, prints at the start of the run what the policy will
//! be fed (the cameras in the order it reads them with their size and the model's input size, the state and action
//! features by name, the normalisation statistics, the tokenizer), and trains a round on it. The Hub's copy stores
//! AV1 video, whose decoding `shared/data/tests/av1.rs` checks on a real clip; this one is written in H.264.

use std::path::Path;
use std::process::Command;

use fedvla_aggregator::records::MetricsLine;
use fedvla_data::{CameraSpec, DatasetSpec, DatasetWriter, Episode, Frame, RgbImage};

const TASKS: [&str; 3] = [
    "Pick up the cube and place it in the box.",
    "Pick up the red cube and put it on the left.",
    "Place the cube back where it was.",
];
const EPISODES: usize = 6;
const FRAMES: usize = 8;
const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;

/// Joint `j` of frame `t` of `episode`: distinct per joint, so that a mix-up of names and values shows.
fn joint(episode: usize, t: usize, j: usize) -> f32 {
    (10 * j) as f32 + episode as f32 - 0.5 * t as f32
}

fn write_dataset(root: &Path) {
    let cameras = ["top", "wrist"].map(|name| CameraSpec::new(name, HEIGHT, WIDTH)).to_vec();
    let mut writer = DatasetWriter::create(root, DatasetSpec::so100(cameras)).unwrap();
    for episode in 0..EPISODES {
        let frames = (0..FRAMES)
            .map(|t| Frame {
                state: (0..6).map(|j| joint(episode, t, j)).collect(),
                action: (0..6).map(|j| joint(episode, t + 1, j)).collect(),
                images: (0..2u8)
                    .map(|c| {
                        let shade = 60 * c + 20 * (t as u8 % 4) + episode as u8;
                        RgbImage::new(WIDTH, HEIGHT, vec![shade; (WIDTH * HEIGHT * 3) as usize]).unwrap()
                    })
                    .collect(),
            })
            .collect();
        writer.add_episode(&Episode { task: TASKS[episode % TASKS.len()].into(), frames }).unwrap();
    }
    writer.finish().unwrap();
}

#[test]
fn a_pickplace_shaped_dataset_runs_and_its_inputs_are_printed_first() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("pickplace");
    write_dataset(&data);
    let outputs = tmp.path().join("outputs");
    let run_config = format!(
        "model-size=tiny dataset={} num-server-rounds=1 local-steps=1 batch-size=2 rollout-episodes=0 \
         client-rollout-episodes=0 min-clients=2 min-fit=2 output-dir={}",
        data.display(),
        outputs.display()
    );
    let output = Command::new(env!("CARGO_BIN_EXE_fedvla"))
        .args(["simulate", "--clients", "2", "--run-config", &run_config])
        .output()
        .expect("running fedvla simulate");
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "simulate failed:\n{stdout}\n{}", String::from_utf8_lossy(&output.stderr));

    // What the policy is fed, before anything trains: the cameras in dataset order at their recorded size, the
    // joints by name, the dataset's own statistics, the tokenizer.
    let mean = |j: usize| {
        let sum: f32 = (0..EPISODES).flat_map(|e| (0..FRAMES).map(move |t| joint(e, t, j))).sum();
        format!("{:.3}", sum / (EPISODES * FRAMES) as f32)
    };
    let state_mean = (0..6).map(mean).collect::<Vec<_>>().join(", ");
    let names =
        r#"["shoulder_pan.pos","shoulder_lift.pos","elbow_flex.pos","wrist_flex.pos","wrist_roll.pos","gripper.pos"]"#;
    let expected = [
        format!("{} episodes, {} frames at 30 fps, tasks {TASKS:?}", EPISODES, EPISODES * FRAMES),
        format!("camera 0: observation.images.top ({WIDTH}x{HEIGHT}, resized with padding to "),
        format!("camera 1: observation.images.wrist ({WIDTH}x{HEIGHT}, resized with padding to "),
        format!("observation.state: {names}\n    normalised with mean [{state_mean}], std ["),
        format!("action: {names}\n    normalised with mean ["),
        "tokenizer: ".to_owned(),
    ];
    let first_round = stdout.find("rounds done").unwrap_or(stdout.len());
    for line in &expected {
        let at = stdout.find(line.as_str()).unwrap_or_else(|| panic!("{line:?} not printed:\n{stdout}"));
        assert!(at < first_round, "{line:?} printed after the run, not at its start:\n{stdout}");
    }
    let top = stdout.find("camera 0: observation.images.top").unwrap();
    assert!(top < stdout.find("camera 1: observation.images.wrist").unwrap(), "the cameras in dataset order");

    // And it trained: the round's metrics, with both clients' updates.
    let run = std::fs::read_dir(&outputs).unwrap().next().expect("a run directory").unwrap().path();
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let lines: Vec<MetricsLine> = metrics.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let round = lines.iter().find(|l| l.round == 1).unwrap_or_else(|| panic!("no round 1 in:\n{metrics}"));
    assert_eq!(round.clients.len(), 2, "both clients' updates in round 1: {metrics}");
}
