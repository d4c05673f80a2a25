//! `fedvla loadtest`: a server of the linreg workload and N WebSocket volunteers in one process, over loopback
//! only, bounded in volunteers, rounds and time, and what it measured ([`LoadReport`]): how long tasks take to
//! reach the volunteers and updates to be acknowledged, the server's CPU, the process's memory, and every update
//! accepted, refused with a reason, or lost. The volunteers run the real round loop (`run_client`) with linreg's
//! trainer, whose updates are valid ones of its trainable tensors, so what is measured is the server's work.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::Context;
use fedvla_aggregator::config::RunConfig;
use fedvla_aggregator::records::{MetricsLine, read_metrics};
use fedvla_aggregator::run_dir::RunDir;
use fedvla_app::server;
use fedvla_federation::{ClientEvent, ClientOptions, Introduction, identify, run_client};
use fedvla_workloads::linreg::{LinRegTrainer, LinRegWorkload};
use fedvla_workloads::workload::server_parts;
use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;

use crate::native_client::{NativeTransport, simulated_identity};
use crate::runs::boxed;

/// At most this many volunteers: each is two sockets of this one process.
pub const MAX_CLIENTS: usize = 5_000;
pub const MAX_ROUNDS: u64 = 100;
/// Shards of the linreg data the volunteers share (volunteer i trains on shard i mod this): a shard per volunteer
/// would make the volunteers' own data, not the server, the process's memory.
const SHARDS: usize = 8;
/// The server's threads' name: their CPU time is the server's.
const SERVER_THREADS: &str = "fedvla-server";
/// Linux's `USER_HZ`, the unit of /proc's CPU times.
const TICKS_PER_SECOND: f64 = 100.0;

/// What to run.
#[derive(Debug, Clone)]
pub struct LoadOptions {
    pub clients: usize,
    pub rounds: u64,
    /// Each volunteer's linreg steps a round.
    pub local_steps: u32,
    /// The whole run is stopped after this; what it measured so far is reported.
    pub time_limit: Duration,
    /// Where the run directory is created.
    pub output_dir: PathBuf,
}

/// What a load test measured; `--json` writes it, and the test reads it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LoadReport {
    pub clients: usize,
    pub rounds: u64,
    pub completed_rounds: u64,
    pub timed_out: bool,
    /// The run configuration keys raised above their defaults for this run (`key=value`): every volunteer joins
    /// from 127.0.0.1, past the per-address bounds a server open to strangers keeps, and holds a WebSocket and,
    /// while it downloads the round's model, an HTTP connection.
    pub raised: Vec<String>,
    pub joined: usize,
    /// From the start to the last volunteer's welcome.
    pub join_seconds: f64,
    pub wall_seconds: f64,
    /// From the round's opening (the last welcome for round 1, the previous round's close reaching the first
    /// volunteer after that) to each volunteer's task.
    pub task_dispatch_ms: Latencies,
    /// From a volunteer's last frame of an update to its round's close reaching it: the protocol acknowledges an
    /// update with the close of its round (a refusal comes sooner, as an error).
    pub update_ack_ms: Latencies,
    pub updates: UpdateCounts,
    /// CPU time of the server's threads (its runtime's workers and blocking pool), user and system.
    pub server_cpu_seconds: f64,
    pub process_cpu_seconds: f64,
    /// Resident memory of the whole process (the server and every volunteer): its peak, and at the end.
    pub peak_rss_bytes: u64,
    pub final_rss_bytes: u64,
    /// Volunteers whose round loop ended in an error, with it.
    pub client_failures: Vec<String>,
    pub run_dir: PathBuf,
}

/// Percentiles (nearest rank) of a set of durations, in milliseconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Latencies {
    pub count: usize,
    pub p50: f64,
    pub p95: f64,
    pub p99: f64,
    pub max: f64,
}

impl Latencies {
    fn of(mut ms: Vec<f64>) -> Self {
        ms.sort_by(f64::total_cmp);
        let rank = |p: f64| ms[((p * ms.len() as f64).ceil() as usize).clamp(1, ms.len()) - 1];
        match ms.last() {
            None => Self::default(),
            Some(&max) => Self { count: ms.len(), p50: rank(0.5), p95: rank(0.95), p99: rank(0.99), max },
        }
    }
}

/// Every update a volunteer sent, by what became of it (from the run's `metrics.jsonl`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct UpdateCounts {
    pub sent: u64,
    pub accepted: u64,
    /// Refused, by the code of the reason.
    pub refused: BTreeMap<String, u64>,
    /// Sent, and neither accepted nor refused with a reason.
    pub lost: u64,
}

/// One volunteer's events, each with when it happened.
struct VolunteerLog {
    shard: usize,
    events: Vec<(Instant, ClientEvent)>,
    error: Option<String>,
}

/// Runs the load test; an error only when it could not run (a volunteer's failure is reported, not an error).
pub fn run(options: &LoadOptions) -> anyhow::Result<LoadReport> {
    let LoadOptions { clients, rounds, local_steps, time_limit, ref output_dir } = *options;
    anyhow::ensure!((1..=MAX_CLIENTS).contains(&clients), "--clients must be 1 to {MAX_CLIENTS}");
    anyhow::ensure!((1..=MAX_ROUNDS).contains(&rounds), "--rounds must be 1 to {MAX_ROUNDS}");
    let (config, raised) = load_config(clients, rounds, local_steps, time_limit)?;
    let run_dir = RunDir::create(output_dir, &config)?;
    let runtime = |name: &str| {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name(name)
            // Blocking threads that ended would take their CPU time with them.
            .thread_keep_alive(time_limit + Duration::from_secs(60))
            .enable_all()
            .build()
            .context("tokio runtime")
    };
    let (server_rt, clients_rt) = (runtime(SERVER_THREADS)?, runtime("fedvla-clients")?);
    let parts = server_parts(&LinRegWorkload::from_config(&config), config.clone(), run_dir.clone()).map_err(boxed)?;
    let start = Instant::now();
    let handle = server_rt.block_on(async {
        let listener = TcpListener::bind("127.0.0.1:0").await.context("binding 127.0.0.1:0")?;
        anyhow::Ok(server::start(parts, listener)?)
    })?;
    let url = format!("ws://{}", handle.addr());
    let cancel = handle.cancel_token();
    let partitioning = config.partitioning;
    let (logs, timed_out) = clients_rt.block_on(async move {
        let volunteers = (0..clients).map(|i| tokio::spawn(volunteer(url.clone(), i, partitioning)));
        let all = futures_util::future::join_all(volunteers);
        tokio::pin!(all);
        let timed_out = tokio::select! {
            logs = &mut all => return (logs, false),
            () = tokio::time::sleep(time_limit) => true,
        };
        // Shutting down tells every volunteer, which then ends.
        cancel.cancel();
        (all.await, timed_out)
    });
    let status = server_rt.block_on(handle.finish());
    let wall_seconds = start.elapsed().as_secs_f64();
    let completed_rounds = match status {
        Ok(status) => status.completed_rounds,
        Err(e) if timed_out => {
            tracing::warn!(error = %e, "the server stopped at the time limit");
            read_metrics(run_dir.path())?.last().map_or(0, |line| line.round)
        }
        Err(e) => return Err(e.into()),
    };
    let logs: Vec<VolunteerLog> = logs.into_iter().collect::<Result<_, _>>().context("a volunteer panicked")?;
    let metrics = read_metrics(run_dir.path())?;
    let (peak_rss_bytes, final_rss_bytes) = crate::aggregation_memory::rss()?;
    Ok(LoadReport {
        clients,
        rounds,
        completed_rounds,
        timed_out,
        raised,
        joined: logs.iter().filter(|l| joined_at(l).is_some()).count(),
        join_seconds: all_joined(&logs).map_or(0.0, |t| t.duration_since(start).as_secs_f64()),
        wall_seconds,
        task_dispatch_ms: Latencies::of(dispatch_ms(&logs)),
        update_ack_ms: Latencies::of(ack_ms(&logs)),
        updates: count_updates(&logs, &metrics),
        server_cpu_seconds: cpu_seconds(Some(SERVER_THREADS))?,
        process_cpu_seconds: cpu_seconds(None)?,
        peak_rss_bytes,
        final_rss_bytes,
        client_failures: logs.iter().filter_map(|l| Some(format!("load-{}: {}", l.shard, l.error.as_ref()?))).collect(),
        run_dir: run_dir.path().to_owned(),
    })
}

/// The run configuration: the default's, with the linreg workload, every volunteer sampled every round (a round
/// starts once all are connected), and the bounds raised to let `clients` volunteers of one address join and
/// download their models at once; returns the raised keys too.
fn load_config(
    clients: usize,
    rounds: u64,
    local_steps: u32,
    time_limit: Duration,
) -> anyhow::Result<(RunConfig, Vec<String>)> {
    let defaults = RunConfig::default();
    let joins = (clients as u32).max(defaults.joins_per_address_per_minute);
    // A volunteer holds its WebSocket and, while it downloads the round's model, an HTTP connection besides.
    let connections = (2 * clients + 64).max(defaults.max_connections);
    let raised: Vec<String> = [
        ("joins-per-address-per-minute", joins as usize, defaults.joins_per_address_per_minute as usize),
        ("max-connections", connections, defaults.max_connections),
    ]
    .into_iter()
    .filter(|(_, value, default)| value > default)
    .map(|(key, value, _)| format!("{key}={value}"))
    .collect();
    let config = defaults.with_overrides(&format!(
        "workload=linreg num-clients={SHARDS} min-clients={clients} min-fit=1 fraction-fit=1.0 \
         num-server-rounds={rounds} eval-every={rounds} rollout-episodes=0 client-rollout-episodes=0 \
         local-steps={local_steps} round-deadline-ms={} {}",
        time_limit.as_millis(),
        raised.join(" ")
    ))?;
    Ok((config, raised))
}

/// Volunteer `load-<i>` on the shard the server binds to its key (round-robin: i mod [`SHARDS`]) until the run
/// finishes, recording its events.
async fn volunteer(url: String, i: usize, partitioning: fedvla_aggregator::config::Partitioning) -> VolunteerLog {
    let mut events = Vec::new();
    let result = async {
        let mut transport = NativeTransport::connect(&url).await.map_err(|e| format!("connect: {e}"))?;
        let name = format!("load-{i}");
        let intro = Introduction { name: name.clone(), auth_token: None, shard: None, own_dataset: false };
        let admission =
            identify(&mut transport, &simulated_identity(&name), &intro).await.map_err(|e| format!("identify: {e}"))?;
        let mut trainer = LinRegTrainer::new(admission.setup.shard_index as usize, partitioning);
        let options = ClientOptions { session: admission.session, data: None };
        let record = |event| events.push((Instant::now(), event));
        run_client(&mut transport, &mut trainer, &options, record).await.map_err(|e| e.to_string())?;
        Ok::<_, String>(())
    }
    .await;
    VolunteerLog { shard: i, events, error: result.err() }
}

fn joined_at(log: &VolunteerLog) -> Option<Instant> {
    log.events.iter().find_map(|(t, e)| matches!(e, ClientEvent::Joined { .. }).then_some(*t))
}

/// When the last volunteer was welcomed (round 1 opens then).
fn all_joined(logs: &[VolunteerLog]) -> Option<Instant> {
    logs.iter().filter_map(joined_at).max()
}

/// When `round`'s close first reached a volunteer.
fn first_close(logs: &[VolunteerLog], round: u64) -> Option<Instant> {
    let closes = logs.iter().flat_map(|l| &l.events);
    closes
        .filter_map(|(t, e)| matches!(e, ClientEvent::RoundClosed { round: r, .. } if *r == round).then_some(*t))
        .min()
}

fn dispatch_ms(logs: &[VolunteerLog]) -> Vec<f64> {
    let joined = all_joined(logs);
    let mut opened = BTreeMap::new();
    let mut out = Vec::new();
    for (t, event) in logs.iter().flat_map(|l| &l.events) {
        let ClientEvent::Task { round, .. } = event else { continue };
        let opening =
            *opened.entry(*round).or_insert_with(|| if *round <= 1 { joined } else { first_close(logs, round - 1) });
        if let Some(opening) = opening {
            out.push(t.saturating_duration_since(opening).as_secs_f64() * 1e3);
        }
    }
    out
}

fn ack_ms(logs: &[VolunteerLog]) -> Vec<f64> {
    let mut out = Vec::new();
    for log in logs {
        for (sent, event) in &log.events {
            let ClientEvent::Uploaded { round, .. } = event else { continue };
            let closed = log.events.iter().find_map(|(t, e)| {
                matches!(e, ClientEvent::RoundClosed { round: r, .. } if r == round && t >= sent).then_some(*t)
            });
            if let Some(closed) = closed {
                out.push(closed.duration_since(*sent).as_secs_f64() * 1e3);
            }
        }
    }
    out
}

/// Each update a volunteer sent, as its round's metrics line records its client: accepted, refused by a code
/// (or left out of the aggregate, `dropped_update`), or, with no record or no reason, lost.
fn count_updates(logs: &[VolunteerLog], metrics: &[MetricsLine]) -> UpdateCounts {
    let mut counts = UpdateCounts::default();
    for log in logs {
        let client_id = log.events.iter().find_map(|(_, e)| match e {
            ClientEvent::Joined { client_id } => Some(*client_id),
            _ => None,
        });
        for (_, event) in &log.events {
            let ClientEvent::Uploaded { round, .. } = event else { continue };
            counts.sent += 1;
            let record = metrics
                .iter()
                .filter(|line| line.round == *round)
                .flat_map(|line| &line.clients)
                .find(|c| Some(c.client_id) == client_id);
            let reason = record.and_then(|c| {
                c.refused.first().cloned().or_else(|| c.dropped.as_ref().map(|_| "dropped_update".to_owned()))
            });
            match (record, reason) {
                (Some(c), _) if c.accepted => counts.accepted += 1,
                (_, Some(code)) => *counts.refused.entry(code).or_default() += 1,
                _ => counts.lost += 1,
            }
        }
    }
    counts
}

/// User and system CPU seconds of this process, or of its threads whose name starts with `threads`.
fn cpu_seconds(threads: Option<&str>) -> anyhow::Result<f64> {
    let ticks = |stat: &str| -> Option<(String, f64)> {
        let (head, rest) = stat.rsplit_once(") ")?;
        let name = head.split_once(" (")?.1.to_owned();
        // After the name: state (field 3), ..., utime (14), stime (15).
        let fields: Vec<&str> = rest.split_whitespace().collect();
        let used: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
        Some((name, used / TICKS_PER_SECOND))
    };
    let read = |path: &Path| std::fs::read_to_string(path).with_context(|| path.display().to_string());
    let Some(prefix) = threads else {
        let stat = read(Path::new("/proc/self/stat"))?;
        return ticks(&stat).map(|(_, s)| s).context("/proc/self/stat: unexpected format");
    };
    let mut total = 0.0;
    for task in std::fs::read_dir("/proc/self/task").context("/proc/self/task")? {
        // A thread that ended since the listing has nothing to add.
        let Ok(stat) = read(&task?.path().join("stat")) else { continue };
        if let Some((name, seconds)) = ticks(&stat).filter(|(name, _)| name.starts_with(prefix)) {
            tracing::trace!(name, seconds, "server thread");
            total += seconds;
        }
    }
    Ok(total)
}

impl fmt::Display for LoadReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mb = |bytes: u64| bytes as f64 / 1e6;
        let line = |l: &Latencies| {
            format!("p50 {:.1}  p95 {:.1}  p99 {:.1}  max {:.1}  (n = {})", l.p50, l.p95, l.p99, l.max, l.count)
        };
        writeln!(
            f,
            "{} volunteers x {} rounds of the linreg workload over loopback WebSockets (server and volunteers in this \
             process)",
            self.clients, self.rounds
        )?;
        match self.raised.is_empty() {
            true => writeln!(f, "no bound raised: the defaults let {} volunteers of one address in", self.clients)?,
            false => writeln!(
                f,
                "raised for this run (every volunteer joins from 127.0.0.1, and downloads each round's model on a \
                 second connection): {}",
                self.raised.join(", ")
            )?,
        }
        writeln!(
            f,
            "joined: {} of {} in {:.1} s; {} of {} rounds in {:.1} s{}",
            self.joined,
            self.clients,
            self.join_seconds,
            self.completed_rounds,
            self.rounds,
            self.wall_seconds,
            if self.timed_out { " (stopped at the time limit)" } else { "" }
        )?;
        writeln!(
            f,
            "task dispatch, ms (round opened -> task at the volunteer):       {}",
            line(&self.task_dispatch_ms)
        )?;
        writeln!(f, "update acknowledgement, ms (last frame -> round close at it):    {}", line(&self.update_ack_ms))?;
        let u = &self.updates;
        let refused: u64 = u.refused.values().sum();
        let reasons: Vec<String> = u.refused.iter().map(|(code, n)| format!("{code}: {n}")).collect();
        let reasons = if reasons.is_empty() { String::new() } else { format!(" ({})", reasons.join(", ")) };
        writeln!(f, "updates: {} sent, {} accepted, {refused} refused{reasons}, {} lost", u.sent, u.accepted, u.lost)?;
        writeln!(
            f,
            "server CPU: {:.1} s over {:.1} s ({:.0}% of one core); the whole process {:.1} s",
            self.server_cpu_seconds,
            self.wall_seconds,
            100.0 * self.server_cpu_seconds / self.wall_seconds.max(1e-9),
            self.process_cpu_seconds
        )?;
        writeln!(
            f,
            "resident memory of the process (server and every volunteer): peak {:.0} MB, at the end {:.0} MB",
            mb(self.peak_rss_bytes),
            mb(self.final_rss_bytes)
        )?;
        for failure in &self.client_failures {
            writeln!(f, "volunteer failed: {failure}")?;
        }
        write!(f, "run directory: {}", self.run_dir.display())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_are_nearest_rank() {
        let l = Latencies::of((1..=100).rev().map(f64::from).collect());
        assert_eq!((l.count, l.p50, l.p95, l.p99, l.max), (100, 50.0, 95.0, 99.0, 100.0));
        assert_eq!(Latencies::of(vec![7.0]).p99, 7.0);
        assert_eq!(Latencies::of(Vec::new()), Latencies::default());
    }

    #[test]
    fn the_per_address_bounds_are_raised_only_past_their_defaults() {
        let (config, raised) = load_config(100, 2, 5, Duration::from_secs(60)).unwrap();
        assert_eq!(raised, ["joins-per-address-per-minute=100"]);
        assert_eq!((config.joins_per_address_per_minute, config.max_connections), (100, 1024));
        let (config, raised) = load_config(1000, 2, 5, Duration::from_secs(60)).unwrap();
        assert_eq!(raised, ["joins-per-address-per-minute=1000", "max-connections=2064"]);
        assert_eq!(config.min_clients, 1000);
    }
}
