//! Crash safety of the real `fedvla serve` process on the linreg workload. Killed (SIGKILL) at seeded random
//! points of its rounds several times in a row and resumed with `--resume` each time, it loses no completed round,
//! shows no half-written file under a name a reader opens (its temporaries are hidden names, swept on resume), and
//! ends on the model of an uninterrupted run, round by round. With its output directory on a filesystem that fills
//! up, it stops with an error naming the path and the full device, and the rounds before stay intact and resumable.
//!
//! `FEDVLA_KILL_TRIALS` is the number of kills in a row (3 by default; the closing note's figure is 10:
//! `FEDVLA_KILL_TRIALS=10 cargo test -p fedvla-server --test crash -- --nocapture`), `FEDVLA_KILL_SEED` the seed
//! of their timing.

mod common;

use std::ffi::OsStr;
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::*;
use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::MetricsLine;
use fedvla_aggregator::run_dir::{CONFIG_FILE, METRICS_FILE, MODELS_DIR, TRAINABLE_FILE};
use fedvla_federation::{ClientError, ClientSummary, NamedTensors};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use tokio::sync::Semaphore;
use tokio::task::JoinHandle;

const CLIENTS: usize = 3;

/// One life of `fedvla serve`: the process, the WebSocket URL it listens on, and its stderr (a file, read once
/// the process exited). Dropped, it is killed.
struct Server {
    child: Child,
    url: String,
    stderr: PathBuf,
}

impl Server {
    /// Starts `fedvla serve ARGS` on a free loopback port and waits until it accepts connections.
    async fn start(args: &[&OsStr], stderr: PathBuf) -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let addr = format!("127.0.0.1:{port}");
        let child = Command::new(env!("CARGO_BIN_EXE_fedvla"))
            .arg("serve")
            .args(args)
            .args(["--run-config", &format!("listen={addr}")])
            .stdout(Stdio::null())
            .stderr(File::create(&stderr).unwrap())
            .spawn()
            .expect("fedvla starts");
        let mut server = Self { child, url: format!("ws://{addr}"), stderr };
        let started = Instant::now();
        while tokio::net::TcpStream::connect(&addr).await.is_err() {
            if let Some(status) = server.child.try_wait().unwrap() {
                panic!("fedvla serve exited before listening ({status}):\n{}", server.stderr_text());
            }
            assert!(started.elapsed() < Duration::from_secs(60), "fedvla serve not listening within 60 s");
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        server
    }

    /// SIGKILL; whether the process was still running when it came.
    fn kill(&mut self) -> bool {
        let running = self.child.try_wait().unwrap().is_none();
        self.child.kill().unwrap();
        self.child.wait().unwrap();
        running
    }

    /// Waits (at most `within`) for the process to end by itself; its exit status and stderr.
    async fn exit(&mut self, within: Duration) -> (ExitStatus, String) {
        let started = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return (status, self.stderr_text());
            }
            assert!(started.elapsed() < within, "fedvla serve still running after {within:?}:\n{}", self.stderr_text());
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    fn stderr_text(&self) -> String {
        fs::read_to_string(&self.stderr).unwrap_or_default()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The federation's volunteers `client-0..2`, each on its own shard, joining `url`; each training waits for a
/// permit from `gate` when there is one.
fn join_clients(url: &str, gate: Option<&Arc<Semaphore>>) -> Vec<JoinHandle<Result<ClientSummary, ClientError>>> {
    (0..CLIENTS)
        .map(|shard| {
            let (trainer, _) = TestTrainer::new(shard, None);
            let trainer = match gate {
                Some(gate) => trainer.gated(Arc::clone(gate)),
                None => trainer,
            };
            spawn_trainer_at(url, shard, trainer)
        })
        .collect()
}

/// A run configuration file `file` for the linreg workload writing its runs under `outputs`. Its rounds take
/// milliseconds, so its clients send control messages faster than any real round would let them: their rate is
/// not what is tested here.
fn write_config(file: &Path, outputs: &Path, overrides: &str) -> PathBuf {
    let config =
        config(&format!("workload=linreg output-dir={} max-messages-per-second=100000 {overrides}", outputs.display()));
    fs::write(file, config.to_toml()).unwrap();
    file.to_owned()
}

/// The one run directory `fedvla serve` created under `outputs`.
fn run_dir_in(outputs: &Path) -> PathBuf {
    let runs: Vec<PathBuf> = fs::read_dir(outputs).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(runs.len(), 1, "{runs:?}");
    runs[0].clone()
}

fn model_file(dir: &Path, round: u64) -> PathBuf {
    dir.join(MODELS_DIR).join(format!("round_{round}")).join(TRAINABLE_FILE)
}

/// A run of `config_file` from start to finish, never interrupted: its run directory, and its wall time per
/// round.
async fn uninterrupted(config_file: &Path, outputs: &Path, stderr: PathBuf) -> (PathBuf, Duration) {
    let mut server = Server::start(&[OsStr::new("--config"), config_file.as_os_str()], stderr).await;
    let started = Instant::now();
    let clients = join_clients(&server.url, None);
    let (status, stderr) = server.exit(Duration::from_secs(300)).await;
    assert!(status.success(), "{stderr}");
    for client in clients {
        client.await.unwrap().unwrap();
    }
    let dir = run_dir_in(outputs);
    let rounds = RunConfig::load(&dir.join(CONFIG_FILE)).unwrap().num_server_rounds;
    (dir, started.elapsed() / rounds as u32)
}

/// Reads the run directory as a reader after a crash would, and checks nothing in it is half-written: the metrics
/// file ends with a whole line, every line parses and the rounds follow each other from 0, every completed round's
/// model loads and has the checksum its line records, and every other file under a name that is not a temporary
/// parses whole. Returns each completed round's model checksum in order, and the temporaries (hidden names a
/// reader never opens) it passed over.
fn completed_rounds(dir: &Path) -> (Vec<u32>, Vec<String>) {
    let text = match fs::read_to_string(dir.join(METRICS_FILE)) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
        Err(e) => panic!("{e}"),
    };
    assert!(text.is_empty() || text.ends_with('\n'), "a torn metrics line: {text:?}");
    let mut checksums = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line: MetricsLine = serde_json::from_str(line).unwrap_or_else(|e| panic!("metrics line {i}: {e}: {line}"));
        assert_eq!(line.round, i as u64, "rounds follow each other");
        let model = NamedTensors::from_safetensors(&fs::read(model_file(dir, line.round)).unwrap()).unwrap();
        assert_eq!(model.checksum(), line.model_crc32, "round {}'s model is the one its line records", line.round);
        checksums.push(line.model_crc32);
    }
    (checksums, check_files_whole(dir))
}

/// Parses every file under `dir` whose kind is known (JSON, TOML, safetensors); the temporaries passed over, by
/// their paths in `dir`.
fn check_files_whole(dir: &Path) -> Vec<String> {
    let mut temporaries = Vec::new();
    for entry in fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let extension = path.extension().and_then(OsStr::to_str).unwrap_or_default();
        let whole = |ok: bool| assert!(ok, "half-written: {}", path.display());
        if fedvla_fs::is_temporary(&name) || (path.is_dir() && extension == "tmp") {
            temporaries.push(name);
        } else if path.is_dir() {
            temporaries.extend(check_files_whole(&path).into_iter().map(|inner| format!("{name}/{inner}")));
        } else if extension == "json" {
            whole(serde_json::from_slice::<serde_json::Value>(&fs::read(&path).unwrap()).is_ok());
        } else if extension == "toml" {
            whole(RunConfig::load(&path).is_ok());
        } else if extension == "safetensors" {
            whole(NamedTensors::from_safetensors(&fs::read(&path).unwrap()).is_ok());
        }
    }
    temporaries
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// The server SIGKILLed `FEDVLA_KILL_TRIALS` times in a row, each time at a seeded random moment within about two
/// rounds of it accepting connections (joins, training, aggregation, saving), and resumed: after every kill the
/// completed rounds are those before it or more, each equal to the uninterrupted run's round, and nothing
/// half-written is visible; the run resumed to its end equals the uninterrupted run byte for byte.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killed_at_random_points_and_resumed_ends_on_the_uninterrupted_model() {
    let trials: usize = env_or("FEDVLA_KILL_TRIALS", 3);
    let seed: u64 = env_or("FEDVLA_KILL_SEED", 2026);
    // Room for every life to complete a couple of rounds before the last one finishes the run.
    let rounds = 3 * trials as u64 + 3;
    let work = tempfile::tempdir().unwrap();
    let overrides = format!("num-server-rounds={rounds}");
    let reference_outputs = work.path().join("uninterrupted");
    let reference_config = write_config(&work.path().join("uninterrupted.toml"), &reference_outputs, &overrides);
    let (reference, per_round) =
        uninterrupted(&reference_config, &reference_outputs, work.path().join("uninterrupted.stderr")).await;
    let (expected, _) = completed_rounds(&reference);
    assert_eq!(expected.len() as u64, rounds + 1);

    let outputs = work.path().join("killed");
    let config_file = write_config(&work.path().join("killed.toml"), &outputs, &overrides);
    let mut rng = StdRng::seed_from_u64(seed);
    let mut dir: Option<PathBuf> = None;
    let mut completed = 0;
    let mut kills = Vec::new();
    for trial in 0..=trials {
        let args = match &dir {
            None => [OsStr::new("--config"), config_file.as_os_str()],
            Some(dir) => [OsStr::new("--resume"), dir.as_os_str()],
        };
        let mut server = Server::start(&args, work.path().join(format!("life-{trial}.stderr"))).await;
        let clients = join_clients(&server.url, None);
        let dir = dir.get_or_insert_with(|| run_dir_in(&outputs)).clone();
        if trial == trials {
            let (status, stderr) = server.exit(Duration::from_secs(300)).await;
            assert!(status.success(), "the last life finishes the run:\n{stderr}");
            for client in clients {
                client.await.unwrap().unwrap();
            }
            let (checksums, temporaries) = completed_rounds(&dir);
            assert_eq!(temporaries, Vec::<String>::new(), "a finished run leaves no temporary");
            assert_eq!(checksums, expected, "every round equals the uninterrupted run's");
            assert_eq!(
                fs::read(model_file(&dir, rounds)).unwrap(),
                fs::read(model_file(&reference, rounds)).unwrap(),
                "the final model, byte for byte"
            );
            break;
        }
        let delay = per_round.mul_f64(rng.random_range(0.0..2.0));
        tokio::time::sleep(delay).await;
        assert!(server.kill(), "life {trial} finished the run before its kill at {delay:?}");
        for client in clients {
            client.abort();
        }
        let (checksums, temporaries) = completed_rounds(&dir);
        assert!(
            checksums.len() >= completed,
            "kill {trial}: {completed} rounds completed before, {} now",
            checksums.len()
        );
        assert_eq!(
            checksums,
            expected[..checksums.len()],
            "kill {trial}: the completed rounds are the uninterrupted run's"
        );
        completed = checksums.len();
        let last = completed.checked_sub(1).map_or("none".into(), |round| format!("0-{round}"));
        kills.push(format!("{delay:.0?}: rounds {last} complete, temporaries {temporaries:?}"));
    }
    println!(
        "kill-and-resume: {trials} SIGKILLs in a row (seed {seed}, {rounds} rounds, {per_round:.0?} a round), no \
         completed round lost, nothing half-written visible, final model equal to the uninterrupted run: {}",
        kills.join("; ")
    );
}

/// A tmpfs of `size` mounted at `dir` while the value lives: a real filesystem that fills up. Mounting needs root
/// (CAP_SYS_ADMIN); without it the full-disk test skips, saying why.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, size: &str) -> Result<Self, String> {
        let output = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir)
            .output()
            .map_err(|e| format!("mount: {e}"))?;
        if output.status.success() {
            Ok(Self(dir.to_owned()))
        } else {
            Err(String::from_utf8_lossy(&output.stderr).trim().to_owned())
        }
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

/// The output directory on a 1 MiB tmpfs, filled up once round 2 is complete: round 3 cannot be saved, and the
/// server exits with an error naming the file and "No space left on device", leaving rounds 0-2 whole, no
/// temporary and no trace of round 3. With space again, `--resume` finishes the run on the uninterrupted model.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_output_disk_stops_the_run_with_a_clear_error_and_keeps_earlier_rounds() {
    let work = tempfile::tempdir().unwrap();
    let disk = work.path().join("disk");
    fs::create_dir(&disk).unwrap();
    let _mounted = match Tmpfs::mount(&disk, "1m") {
        Ok(mounted) => mounted,
        Err(why) => {
            eprintln!("SKIPPED: cannot mount a tmpfs to fill ({why}); run as root to test a full output disk");
            return;
        }
    };
    let overrides = "num-server-rounds=4";
    let reference_outputs = work.path().join("uninterrupted");
    let reference_config = write_config(&work.path().join("uninterrupted.toml"), &reference_outputs, overrides);
    let (reference, _) =
        uninterrupted(&reference_config, &reference_outputs, work.path().join("uninterrupted.stderr")).await;
    let (expected, _) = completed_rounds(&reference);

    let outputs = disk.join("outputs");
    let config_file = write_config(&work.path().join("full.toml"), &outputs, overrides);
    let gate = Arc::new(Semaphore::new(0));
    let mut server =
        Server::start(&[OsStr::new("--config"), config_file.as_os_str()], work.path().join("full.stderr")).await;
    let clients = join_clients(&server.url, Some(&gate));
    gate.add_permits(2 * CLIENTS);
    let dir = run_dir_in(&outputs);
    let started = Instant::now();
    while completed_rounds(&dir).0.len() < 3 {
        assert!(started.elapsed() < Duration::from_secs(60), "rounds 1 and 2 within 60 s");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // Round 3's tasks are out, its training waits for the gate: fill the disk, then let it finish.
    let mut filler = File::create(disk.join("filler")).unwrap();
    let full = loop {
        if let Err(e) = filler.write_all(&[0; 4096]).and_then(|()| filler.sync_all()) {
            break e;
        }
    };
    assert_eq!(full.kind(), std::io::ErrorKind::StorageFull, "{full}");
    gate.add_permits(CLIENTS);
    let (status, stderr) = server.exit(Duration::from_secs(60)).await;
    for client in clients {
        client.abort();
    }
    assert!(!status.success(), "a full disk stops the run:\n{stderr}");
    // What `fedvla serve` ends with, anyhow's report of the error that stopped it.
    let error = &stderr[stderr.rfind("Error: ").unwrap_or_else(|| panic!("no error reported:\n{stderr}"))..];
    assert!(error.contains("No space left on device"), "the error says the disk is full: {error}");
    assert!(error.contains(&dir.display().to_string()), "the error names the path: {error}");
    println!("full disk: {status}, {error}");
    let (checksums, temporaries) = completed_rounds(&dir);
    assert_eq!(checksums, expected[..3], "rounds 0-2 intact");
    assert_eq!(temporaries, Vec::<String>::new(), "the failed writes removed their temporaries");
    assert!(!dir.join(MODELS_DIR).join("round_3").exists());

    drop(filler);
    fs::remove_file(disk.join("filler")).unwrap();
    let mut server =
        Server::start(&[OsStr::new("--resume"), dir.as_os_str()], work.path().join("resumed.stderr")).await;
    let clients = join_clients(&server.url, None);
    let (status, stderr) = server.exit(Duration::from_secs(60)).await;
    assert!(status.success(), "{stderr}");
    for client in clients {
        client.await.unwrap().unwrap();
    }
    assert_eq!(completed_rounds(&dir).0, expected, "resumed with space again, the run ends as the uninterrupted one");
}
