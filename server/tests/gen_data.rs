//! `generate_dataset` writes what the sim's scripted expert does, bit for bit, as a LeRobot v3.0
//! dataset that reads back with its stats, and the same options give the same files; several tasks make
//! one dataset whose episodes cycle through them, each with its own instruction, which LeRobot 0.6.1
//! itself reads (when FEDVLA_LEROBOT_ENV names its checker's chroot, as tests/native-env.sh sets).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use fedvla_data::{FeatureStats, LeRobotDataset, RgbImage};
use fedvla_sim::{
    Arrangement, Camera, FPS, JOINT_COUNT, Scene, TASK, TaskKind, render, run_expert_episode, run_expert_episode_on,
};
use fedvla_workloads::datagen::{
    GenDataOptions, GenProgress, MAX_EPISODE_FRAMES, ensure_unrecorded, generate_dataset, recorded_seeds,
};

const SIZE: u32 = 64;

#[test]
fn expert_episodes_read_back_exactly() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("so100");
    let opts = GenDataOptions { episodes: 2, seed: 0, image_size: SIZE, ..Default::default() };
    let mut events = Vec::new();
    let summary = generate_dataset(&out, &opts, |e| events.push(e)).expect("generate");

    assert_eq!(summary.root, out);
    assert_eq!((summary.episodes, summary.seeds.len()), (2, 2));
    let mut tried: Vec<u64> = summary.seeds.iter().chain(&summary.skipped_seeds).copied().collect();
    tried.sort_unstable();
    assert_eq!(tried, (0..tried.len() as u64).collect::<Vec<_>>(), "seeds are tried in order from --seed");

    let dataset = LeRobotDataset::open(&out).expect("open");
    assert_eq!(dataset.episodes().len(), 2);
    assert_eq!(dataset.len() as u64, summary.frames);
    assert_eq!(dataset.fps(), FPS);
    assert_eq!(dataset.tasks(), [TASK.to_string()]);
    assert_eq!(dataset.camera_keys(), Camera::ALL.map(|c| format!("observation.images.{}", c.name())));

    for (episode, &seed) in dataset.episodes().iter().zip(&summary.seeds) {
        let expert = run_expert_episode(seed, MAX_EPISODE_FRAMES, fedvla_sim::ActionNoise::NONE);
        assert!(expert.success, "seed {seed} was recorded although the expert fails on it");
        assert_eq!(episode.length, expert.states.len(), "seed {seed}");
        assert_eq!(episode.tasks, [TASK.to_string()]);
        for (k, row) in (episode.dataset_from_index..episode.dataset_to_index).enumerate() {
            assert_eq!(dataset.vector("observation.state", row), Some(&expert.states[k][..]), "seed {seed} frame {k}");
            assert_eq!(dataset.vector("action", row), Some(&expert.actions[k][..]), "seed {seed} frame {k}");
        }

        // The first frame of each camera is the freshly placed scene; H.264 keeps it close.
        let scene = Scene::new(seed);
        for camera in Camera::ALL {
            let key = format!("observation.images.{}", camera.name());
            let decoded =
                dataset.camera_frames(&key, episode, &[episode.dataset_from_index]).expect("decode").remove(0);
            assert_eq!((decoded.width, decoded.height), (SIZE, SIZE));
            let distinct: std::collections::BTreeSet<u8> = decoded.data.iter().copied().collect();
            assert!(distinct.len() > 32, "{key} of seed {seed} looks blank: {} distinct values", distinct.len());
            let rendered =
                RgbImage::new(SIZE, SIZE, render(&scene, camera, SIZE as usize, SIZE as usize)).expect("rgb");
            let diff = decoded.mean_abs_diff(&rendered);
            assert!(diff < 4.0, "{key} of seed {seed} differs from the render by {diff}/255 on average");
        }
    }

    // The dataset's stats are the per-episode stats of the stored rows, aggregated.
    let stats = dataset.stats().expect("stats.json");
    for key in ["observation.state", "action"] {
        let per_episode: Vec<FeatureStats> = dataset
            .episodes()
            .iter()
            .map(|e| {
                let rows: Vec<Vec<f64>> = (e.dataset_from_index..e.dataset_to_index)
                    .map(|i| dataset.vector(key, i).expect("row").iter().map(|&v| f64::from(v)).collect())
                    .collect();
                FeatureStats::from_rows(&rows, JOINT_COUNT)
            })
            .collect();
        let recomputed = FeatureStats::aggregate(&per_episode.iter().collect::<Vec<_>>()).expect("two episodes");
        assert_eq!(stats.get(key), Some(&recomputed), "{key}");
    }

    let frame_events = events.iter().filter(|e| matches!(e, GenProgress::Frame { .. })).count();
    assert_eq!(frame_events as u64, summary.frames);
    let written: Vec<u64> = events
        .iter()
        .filter_map(|e| match e {
            GenProgress::EpisodeWritten { seed, .. } => Some(*seed),
            _ => None,
        })
        .collect();
    assert_eq!(written, summary.seeds);
    let skipped: Vec<u64> = events
        .iter()
        .filter_map(|e| match e {
            GenProgress::Skipped { seed, .. } => Some(*seed),
            _ => None,
        })
        .collect();
    assert_eq!(skipped, summary.skipped_seeds);
}

#[test]
fn same_options_write_the_same_files() {
    let dir = tempfile::tempdir().expect("temp dir");
    let opts = GenDataOptions { episodes: 1, seed: 5, image_size: SIZE, ..Default::default() };
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    generate_dataset(&a, &opts, |_| {}).expect("first");
    generate_dataset(&b, &opts, |_| {}).expect("second");
    let (files_a, files_b) = (files(&a), files(&b));
    assert!(files_a.keys().any(|p| p.extension().is_some_and(|e| e == "mp4")));
    assert_eq!(files_a.keys().collect::<Vec<_>>(), files_b.keys().collect::<Vec<_>>());
    for (path, bytes) in &files_a {
        assert!(files_b[path] == *bytes, "{} differs between runs", path.display());
    }
}

#[test]
fn recovery_demonstrations_record_the_expert_goals_from_perturbed_states() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("noisy");
    let opts =
        GenDataOptions { episodes: 2, seed: 0, image_size: SIZE, action_noise_degrees: 2.0, ..Default::default() };
    let summary = generate_dataset(&out, &opts, |_| {}).expect("generate");
    let recorded = recorded_seeds(&out).expect("seeds file").expect("written");
    assert_eq!((recorded.seeds, recorded.action_noise_degrees), (summary.seeds.clone(), 2.0));

    let dataset = LeRobotDataset::open(&out).expect("open");
    let noise = fedvla_sim::ActionNoise::degrees(2.0);
    for (episode, &seed) in dataset.episodes().iter().zip(&summary.seeds) {
        let perturbed = run_expert_episode(seed, MAX_EPISODE_FRAMES, noise);
        let clean = run_expert_episode(seed, MAX_EPISODE_FRAMES, fedvla_sim::ActionNoise::NONE);
        assert!(perturbed.states != clean.states, "seed {seed}: the perturbation changed nothing");
        assert_eq!(episode.length, perturbed.states.len(), "seed {seed}");
        for (k, row) in (episode.dataset_from_index..episode.dataset_to_index).enumerate() {
            assert_eq!(
                dataset.vector("observation.state", row),
                Some(&perturbed.states[k][..]),
                "seed {seed} frame {k}"
            );
            assert_eq!(dataset.vector("action", row), Some(&perturbed.actions[k][..]), "seed {seed} frame {k}");
        }
    }
}

#[test]
fn evaluation_on_recorded_layouts_is_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let opts = GenDataOptions { episodes: 2, seed: 3, image_size: SIZE, ..Default::default() };
    let summary = generate_dataset(dir.path(), &opts, |_| {}).expect("generate");
    let first = summary.seeds[0];
    let err = ensure_unrecorded(dir.path(), 0..first + 1).expect_err("seed recorded");
    assert!(err.to_string().contains(&format!("seed {first}")), "{err}");
    ensure_unrecorded(dir.path(), 0..first).expect("seeds below the recording");
    let held_out = fedvla_workloads::sim_eval::DEFAULT_SEED;
    ensure_unrecorded(dir.path(), held_out..held_out + 50).expect("the default evaluation layouts");
}

#[test]
fn odd_image_sizes_and_existing_datasets_are_refused() {
    let dir = tempfile::tempdir().expect("temp dir");
    let odd = GenDataOptions { episodes: 1, seed: 0, image_size: 63, ..Default::default() };
    let err = generate_dataset(dir.path(), &odd, |_| {}).expect_err("odd size");
    assert!(err.to_string().contains("even"), "{err}");

    let opts = GenDataOptions { episodes: 1, seed: 0, image_size: SIZE, ..Default::default() };
    generate_dataset(dir.path(), &opts, |_| {}).expect("first dataset");
    let err = generate_dataset(dir.path(), &opts, |_| {}).expect_err("dataset exists");
    assert!(format!("{err:#}").contains("refusing to overwrite"), "{err:#}");
}

/// Every file under `root`, by path relative to it.
fn files(root: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut dirs = vec![root.to_path_buf()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).expect("read dir") {
            let path = entry.expect("entry").path();
            if path.is_dir() {
                dirs.push(path);
            } else {
                let bytes = std::fs::read(&path).expect("read");
                out.insert(path.strip_prefix(root).expect("under root").to_path_buf(), bytes);
            }
        }
    }
    out
}

/// `partitioning = "by-layout"` hands the partitioner a recorded dataset's episodes in the order of where the
/// cube starts around the arm, so each client's contiguous run is one region of the table; a dataset the sim did
/// not record (no seeds file) is refused, naming the file.
#[test]
fn by_layout_orders_episodes_by_where_the_cube_starts() {
    use fedvla_aggregator::config::RunConfig;
    use fedvla_sim::task::Layout;
    use fedvla_workloads::datagen::SEEDS_FILE;
    use fedvla_workloads::smolvla::episodes_to_partition;

    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("so100");
    let opts = GenDataOptions { episodes: 6, seed: 0, image_size: 32, ..Default::default() };
    generate_dataset(&out, &opts, |_| {}).expect("generate");
    let dataset = LeRobotDataset::open(&out).expect("open");
    let config = RunConfig::default().with_overrides("partitioning=by-layout").unwrap();
    let episodes = episodes_to_partition(&config, &out, &dataset).expect("ordered");
    let seeds = recorded_seeds(&out).unwrap().unwrap().seeds;
    let azimuths: Vec<f32> = episodes
        .iter()
        .map(|e| {
            let cube = Layout::from_seed(seeds[e.episode_index]).cube_position;
            cube.x.atan2(-cube.y)
        })
        .collect();
    assert_eq!(episodes.len(), 6);
    assert!(azimuths.windows(2).all(|w| w[0] <= w[1]), "ordered by azimuth: {azimuths:?}");
    assert!(azimuths[0] < 0.0 && azimuths[5] > 0.0, "cubes on both sides of the arm: {azimuths:?}");
    let by_episode = RunConfig::default().with_overrides("partitioning=by-episode").unwrap();
    let indices: Vec<usize> =
        episodes_to_partition(&by_episode, &out, &dataset).unwrap().iter().map(|e| e.episode_index).collect();
    assert_eq!(indices, [0, 1, 2, 3, 4, 5], "other partitionings keep index order");

    std::fs::remove_file(out.join(SEEDS_FILE)).unwrap();
    let err = episodes_to_partition(&config, &out, &dataset).expect_err("no seeds");
    assert!(format!("{err:#}").contains(SEEDS_FILE), "{err:#}");
}

/// The tasks of the multi-task datasets below: every task but the first, which the tests above record.
const TASKS: [TaskKind; 3] = [TaskKind::Stack, TaskKind::PushToTarget, TaskKind::PickColour];

/// Each episode's instruction, from the seeds file's seeds and tasks.
fn recorded_instructions(root: &Path) -> Vec<String> {
    let recorded = recorded_seeds(root).expect("seeds file").expect("written");
    (0..recorded.seeds.len()).map(|k| recorded.arrangement_of(k).expect("recorded").instruction()).collect()
}

/// The distinct strings of `strings`, sorted.
fn distinct(strings: &[String]) -> Vec<String> {
    let mut distinct = strings.to_vec();
    distinct.sort();
    distinct.dedup();
    distinct
}

#[test]
fn multi_task_episodes_cycle_through_the_tasks_each_with_its_own_instruction() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("tasks");
    let opts = GenDataOptions { episodes: 4, seed: 0, tasks: TASKS.to_vec(), image_size: 32, ..Default::default() };
    let summary = generate_dataset(&out, &opts, |_| {}).expect("generate");
    let recorded = recorded_seeds(&out).expect("seeds file").expect("written");
    assert_eq!((&recorded.seeds, &recorded.tasks[..]), (&summary.seeds, &TASKS[..]));

    let dataset = LeRobotDataset::open(&out).expect("open");
    let instructions: Vec<String> =
        summary.seeds.iter().enumerate().map(|(k, &seed)| TASKS[k % TASKS.len()].instruction(seed)).collect();
    assert_eq!(recorded_instructions(&out), instructions);
    assert_eq!(distinct(dataset.tasks()), distinct(&instructions), "every instruction is listed, once");
    assert_eq!(dataset.episodes().len(), 4);
    let by_layout = fedvla_aggregator::config::RunConfig::default().with_overrides("partitioning=by-layout").unwrap();
    let azimuths: Vec<f32> = fedvla_workloads::smolvla::episodes_to_partition(&by_layout, &out, &dataset)
        .expect("ordered")
        .iter()
        .map(|e| {
            let k = e.episode_index;
            let cube = Arrangement::from_seed(TASKS[k % TASKS.len()], summary.seeds[k]).subject().position;
            cube.x.atan2(-cube.y)
        })
        .collect();
    assert!(azimuths.windows(2).all(|w| w[0] <= w[1]), "by-layout orders by each task's cube: {azimuths:?}");
    for (k, (episode, &seed)) in dataset.episodes().iter().zip(&summary.seeds).enumerate() {
        let task = TASKS[k % TASKS.len()];
        assert_eq!(recorded.task_of(k), task, "episode {k}");
        assert_eq!(episode.tasks, [instructions[k].clone()], "episode {k} ({task}, seed {seed})");
        let task_index = dataset.tasks().iter().position(|t| *t == instructions[k]);
        let expert = run_expert_episode_on(task, seed, MAX_EPISODE_FRAMES, fedvla_sim::ActionNoise::NONE);
        assert!(expert.success, "{task} seed {seed} was recorded although the expert fails on it");
        assert_eq!(episode.length, expert.states.len(), "{task} seed {seed}");
        for (i, row) in (episode.dataset_from_index..episode.dataset_to_index).enumerate() {
            assert_eq!(dataset.task_index(row), task_index, "{task} seed {seed} frame {i}");
            assert_eq!(dataset.vector("action", row), Some(&expert.actions[i][..]), "{task} seed {seed} frame {i}");
        }
    }
}

#[test]
fn every_goal_records_each_layout_of_pick_colour_once_per_cube_and_only_its_words_differ() {
    let dir = tempfile::tempdir().expect("temp dir");
    let out = dir.path().join("every-goal");
    let tasks = vec![TaskKind::PickColour, TaskKind::CubeInBowl];
    let opts = GenDataOptions {
        episodes: 8,
        seed: 0,
        tasks: tasks.clone(),
        image_size: 32,
        every_goal: true,
        ..Default::default()
    };
    let summary = generate_dataset(&out, &opts, |_| {}).expect("generate");
    let recorded = recorded_seeds(&out).expect("seeds file").expect("written");
    assert_eq!((&recorded.seeds, recorded.subjects.len()), (&summary.seeds, 8));
    let dataset = LeRobotDataset::open(&out).expect("open");
    assert_eq!(dataset.episodes().len(), 8);

    // Pick-colour's episodes (0, 2, 4, 6): one layout, then each cube of it in turn, then the next layout; the
    // cube-in-bowl episodes between them keep to one episode a seed, the cube their seed drew.
    let colour_episodes: Vec<usize> = (0..8).step_by(2).collect();
    let seeds: Vec<u64> = colour_episodes.iter().map(|&k| recorded.seeds[k]).collect();
    let subjects: Vec<usize> = colour_episodes.iter().map(|&k| recorded.subjects[k]).collect();
    assert_eq!(seeds[..3], [seeds[0]; 3], "the first layout thrice: {seeds:?}");
    assert!(seeds[3] > seeds[0], "then a fresh layout: {seeds:?}");
    assert_eq!(subjects, [0, 1, 2, 0]);
    for k in (1..8).step_by(2) {
        let drawn = Arrangement::from_seed(TaskKind::CubeInBowl, recorded.seeds[k]).subject;
        assert_eq!((recorded.task_of(k), recorded.subjects[k]), (TaskKind::CubeInBowl, drawn), "episode {k}");
    }
    let mut all_seeds = recorded.seeds.clone();
    all_seeds.sort_unstable();
    all_seeds.dedup();
    assert_eq!(all_seeds.len(), 6, "three pick-colour episodes share a layout, no other seed repeats: {all_seeds:?}");

    let instructions = recorded_instructions(&out);
    let named: Vec<&str> = colour_episodes[..3].iter().map(|&k| instructions[k].as_str()).collect();
    assert_eq!(
        named,
        ["put the red cube in the bowl", "put the green cube in the bowl", "put the yellow cube in the bowl"]
    );
    let rows = |k: usize| dataset.episodes()[k].dataset_from_index..dataset.episodes()[k].dataset_to_index;
    for k in 0..8 {
        assert_eq!(dataset.episodes()[k].tasks, [instructions[k].clone()], "episode {k}");
        // Each episode is the expert's on its arrangement, frame for frame.
        let arrangement = recorded.arrangement_of(k).expect("recorded");
        let mut actions = Vec::new();
        let noise = fedvla_sim::ActionNoise::NONE;
        let end = fedvla_sim::ExpertEnd::PlanDone;
        let scene =
            fedvla_sim::drive_expert_in(arrangement, recorded.seeds[k], end, MAX_EPISODE_FRAMES, noise, |_, a| {
                actions.push(*a)
            });
        assert!(scene.success(), "episode {k} was recorded although the expert fails on it");
        let recorded_actions: Vec<&[f32]> = rows(k).map(|row| dataset.vector("action", row).expect("action")).collect();
        assert_eq!(recorded_actions, actions.iter().map(|a| &a[..]).collect::<Vec<_>>(), "episode {k}");
    }
    // A layout's three episodes start from the same state and part ways by the cube they go for.
    let first = |k: usize| dataset.vector("observation.state", rows(k).start).expect("state").to_vec();
    assert_eq!((first(0), first(2)), (first(4), first(4)));
    let tenth_action = |k: usize| dataset.vector("action", rows(k).start + 10).expect("action").to_vec();
    assert!(tenth_action(0) != tenth_action(2) && tenth_action(2) != tenth_action(4));
}

/// `dir` of this package, canonical: the LeRobot checker's chroot binds host directories at the same paths.
fn beside_the_package(dir: &str) -> PathBuf {
    std::fs::canonicalize(Path::new(env!("CARGO_MANIFEST_DIR")).join(dir)).unwrap_or_else(|e| panic!("{dir}: {e}"))
}

/// Runs the Python `script` on `args` in LeRobot's chroot at `env` (through the checker's `run.sh`), with `dirs`
/// bound into it; panics with its output when it fails, and returns its last line (the checkers' summary).
fn run_in_lerobot(env: &str, dirs: &[&Path], script: &Path, args: &[&str]) -> String {
    let hostdirs: Vec<String> = dirs.iter().map(|d| d.display().to_string()).collect();
    let output = std::process::Command::new("bash")
        .arg(beside_the_package("../../shared/tools/lerobot-check/run.sh"))
        .arg(env)
        .arg("python3")
        .arg(script)
        .args(args)
        .env("HOSTDIR", hostdirs.join(":"))
        .output()
        .expect("running the LeRobot checker");
    let log = format!("{}{}", String::from_utf8_lossy(&output.stdout), String::from_utf8_lossy(&output.stderr));
    assert!(output.status.success(), "LeRobot refused the dataset:\n{log}");
    String::from_utf8_lossy(&output.stdout).lines().last().unwrap_or_default().to_string()
}

#[test]
fn gen_data_records_the_tasks_asked_for_and_lerobot_reads_each_frames_task() {
    let tmp = tempfile::tempdir().expect("temp dir");
    let dir = std::fs::canonicalize(tmp.path()).unwrap();
    let out = dir.join("cli");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_fedvla"))
        .args([
            "gen-data",
            "--episodes",
            "4",
            "--tasks",
            "stack,cube-in-bowl,pick-colour",
            "--image-size",
            "32",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("fedvla runs");
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let recorded = recorded_seeds(&out).expect("seeds file").expect("written");
    assert_eq!(recorded.tasks, [TaskKind::Stack, TaskKind::CubeInBowl, TaskKind::PickColour]);
    let instructions = recorded_instructions(&out);
    assert_eq!((instructions[1].as_str(), instructions.len()), (TASK, 4));
    assert_eq!(distinct(LeRobotDataset::open(&out).expect("open").tasks()), distinct(&instructions));

    let Ok(env) = std::env::var("FEDVLA_LEROBOT_ENV") else {
        eprintln!("SKIPPED: FEDVLA_LEROBOT_ENV not set; LeRobot's reading of the multi-task dataset not checked");
        return;
    };
    let dataset = out.display().to_string();
    let check_dataset = beside_the_package("../../shared/tools/lerobot-check/check_dataset.py");
    let summary = run_in_lerobot(&env, &[&dir], &check_dataset, &[&dataset]);
    assert!(summary.starts_with("CHECK_DATASET OK"), "{summary}");
    println!("{summary}");
    let scripts = beside_the_package("tests/lerobot");
    let expected = serde_json::to_string(&instructions).unwrap();
    let summary = run_in_lerobot(&env, &[&dir, &scripts], &scripts.join("dataset_tasks.py"), &[&dataset, &expected]);
    assert!(summary.starts_with("CHECK_TASKS OK"), "{summary}");
    assert!(summary.contains(&format!("tasks={}", distinct(&instructions).len())), "{summary}");
    println!("{summary}");
}

/// A wandering offset of 5° leaves the pushed cube off the target on every seed: recording gives up saying which
/// task failed how often, under how much noise.
#[test]
fn recording_that_gives_up_names_the_task_its_expert_fails() {
    let dir = tempfile::tempdir().expect("temp dir");
    let opts = GenDataOptions {
        episodes: 1,
        tasks: vec![TaskKind::PushToTarget],
        image_size: 16,
        action_noise_degrees: 5.0,
        ..Default::default()
    };
    let err = generate_dataset(&dir.path().join("push"), &opts, |_| {}).err().expect("the expert fails");
    let message = format!("{err:#}");
    assert!(message.contains("failed on 11 seeds (0..=10) before 1 episode succeeded"), "{message}");
    assert!(message.contains("under 5° of action noise: push-to-target 0 of 11"), "{message}");
}

#[test]
fn gen_data_refuses_an_unknown_task_naming_the_known_ones() {
    let dir = tempfile::tempdir().expect("temp dir");
    let run = std::process::Command::new(env!("CARGO_BIN_EXE_fedvla"))
        .args(["gen-data", "--episodes", "1", "--tasks", "stack,juggle", "--out"])
        .arg(dir.path().join("never"))
        .output()
        .expect("fedvla runs");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && stderr.contains("\"juggle\""), "{stderr}");
    for task in TaskKind::ALL {
        assert!(stderr.contains(task.name()), "{stderr}");
    }
    assert!(!dir.path().join("never").exists());
}

#[test]
fn the_embedded_dataset_keeps_its_directory_for_the_first_task_and_names_other_tasks() {
    use fedvla_aggregator::config::RunConfig;
    use fedvla_workloads::smolvla::dataset_root;
    assert_eq!(dataset_root(&RunConfig::default()).unwrap(), Path::new("data/so100-sim/200ep_64px_noise2"));
    let tasks = RunConfig::default().with_overrides("dataset-tasks=stack,pick-colour").unwrap();
    assert_eq!(dataset_root(&tasks).unwrap(), Path::new("data/so100-sim/200ep_64px_noise2_stack+pick-colour"));
}
