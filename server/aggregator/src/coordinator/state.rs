//! What the coordinator is made of and what it exchanges: the events connections send it, the updates it
//! collects, the status and model it publishes, and the running state its round loop ([`super`]), a round in
//! flight ([`super::round`]) and closing a round ([`super::close`]) work on.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};

use bytes::Bytes;
use fedvla_federation::codec::{encode_model_deltas, model_deltas_len};
use fedvla_federation::{
    BoxError, Capabilities, DataReport, ErrorCode, Evaluator, NamedTensors, NormalizationStats, RolloutEpisode,
    RoundMetrics, ServerMessage, Strategy, UpdateValues,
};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::screen::NormScreen;
use crate::config::RunConfig;
use crate::control::Controls;
use crate::events::RunObserver;
use crate::records::DataSource;
use crate::run_dir::{ModelExporter, RunDir, RunDirError};
use crate::sessions::Sessions;
use crate::upload_budget::Reservation;

/// What connections tell the coordinator.
#[derive(Debug)]
pub enum Event {
    Joined {
        client_id: u64,
        name: String,
        /// The Ed25519 public key (hex) the client proved: its strategy state follows it when it has no shard.
        public_key: String,
        capabilities: Capabilities,
        /// What the client trains on; `None` when the workload offers no shards (its updates weigh equally).
        data: Option<DataSource>,
        /// What it told of its data on join (moments for federated statistics).
        /// Boxed: joins are rare, the channel's other events many.
        report: Option<Box<DataReport>>,
        outbox: mpsc::UnboundedSender<ServerMessage>,
    },
    Left {
        client_id: u64,
    },
    Update {
        client_id: u64,
        update: Box<UpdateReceived>,
    },
    Metrics {
        client_id: u64,
        metrics: RoundMetrics,
    },
    EvalResult {
        client_id: u64,
        round: u64,
        examples: u64,
        loss: f64,
    },
    /// Sim rollouts of the model version a task started from (videos already stored by HTTP).
    RolloutResult {
        client_id: u64,
        round: u64,
        model_version: u64,
        episodes: Vec<RolloutEpisode>,
    },
    /// A client announced an update (`UpdateHeader`); its frames are on the way.
    Uploading {
        client_id: u64,
    },
    /// Input refused by a connection (already answered with an `Error`); `None` before the client joined.
    Rejected {
        client_id: Option<u64>,
        code: ErrorCode,
    },
}

/// A complete, validated update: the trained tensors, or their delta from the round's global model (which the
/// coordinator, holding that model, adds back).
#[derive(Debug)]
pub struct UpdateReceived {
    pub round: u64,
    pub values: UpdateValues,
    /// What the update header said; the update weighs what the client's shard holds.
    pub claimed_examples: u64,
    pub train_loss: f64,
    /// Bytes of the update's binary frames, headers included.
    pub bytes: u64,
    /// The update's share of the upload budget, ended once the round has taken the update (folded or held), so
    /// that updates queued for a slow fold hold the next uploads back.
    pub reservation: Reservation,
}

/// The global model as served: its version and safetensors bytes, and the version before it, which a volunteer
/// may still ask for when a round closed between its reading the setup (or its task) and its download; and the
/// deltas of the last rounds, which a volunteer holding an earlier version downloads instead of the whole model.
#[derive(Debug, Clone)]
pub struct PublishedModel {
    pub version: u64,
    pub safetensors: Bytes,
    previous: Option<(u64, Bytes)>,
    /// Each version's delta payload from the version before it ([`fedvla_federation::codec::encode_model_delta`]),
    /// oldest first, up to `version` without a gap, as many as make a chain shorter than the whole model (a longer
    /// one is never worth downloading): at most one model's bytes more held.
    deltas: VecDeque<(u64, Bytes)>,
}

impl PublishedModel {
    /// The first model a run serves.
    pub fn first(version: u64, safetensors: Bytes) -> Self {
        Self { version, safetensors, previous: None, deltas: VecDeque::new() }
    }

    /// The model that follows this one, with its delta from this one when it has one (`None`: an f32 run, or a
    /// round that left the model as it was, after which only whole models are served); this one stays
    /// downloadable as the previous version, unless it is the same version.
    pub fn next(&self, version: u64, safetensors: Bytes, delta: Option<Bytes>) -> Self {
        let mut deltas = match delta {
            Some(delta) if version == self.version + 1 => {
                let mut deltas = self.deltas.clone();
                deltas.push_back((version, delta));
                deltas
            }
            _ => VecDeque::new(),
        };
        let chain_len = |d: &VecDeque<(u64, Bytes)>| model_deltas_len(d.len(), d.iter().map(|(_, b)| b.len()).sum());
        while !deltas.is_empty() && chain_len(&deltas) >= safetensors.len() {
            deltas.pop_front();
        }
        // The same version again (round 0's model, published at start and once evaluated) keeps the one before.
        let previous = match version == self.version {
            true => self.previous.clone(),
            false => Some((self.version, self.safetensors.clone())),
        };
        Self { version, safetensors, previous, deltas }
    }

    /// The bytes of `version` while it is the current or the previous one.
    pub fn bytes_of(&self, version: u64) -> Option<&Bytes> {
        match &self.previous {
            _ if version == self.version => Some(&self.safetensors),
            Some((previous, bytes)) if *previous == version => Some(bytes),
            _ => None,
        }
    }

    /// The oldest version the current one is served from as deltas, when any is.
    pub fn deltas_since(&self) -> Option<u64> {
        self.deltas.front().map(|(version, _)| version - 1)
    }

    /// The chain of deltas taking version `from` to `version` ([`encode_model_deltas`]), while every one of them
    /// is kept.
    pub fn deltas(&self, version: u64, from: u64) -> Option<Vec<u8>> {
        let first = self.deltas.iter().position(|(v, _)| *v == from + 1)?;
        let last = self.deltas.iter().position(|(v, _)| *v == version)?;
        (first <= last).then(|| encode_model_deltas(from, self.deltas.range(first..=last).map(|(_, b)| &b[..])))
    }
}

/// Where the run stands, published after every change.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunStatus {
    pub completed_rounds: u64,
    pub connected: usize,
    /// Refused client inputs by error code, since the server started.
    pub rejections: BTreeMap<ErrorCode, u64>,
    /// Round attempts that closed with too few updates.
    pub retried_rounds: u64,
    /// Rounds whose every aggregate failed (or whose evaluation did): the global model stayed as it was.
    pub skipped_rounds: u64,
    /// Updates whose example count claim differed from their shard's training examples (the shard's count was
    /// used).
    pub corrected_claims: u64,
    pub finished: bool,
}

#[derive(Debug, thiserror::Error)]
pub enum CoordinatorError {
    #[error("cancelled")]
    Cancelled,
    #[error(transparent)]
    RunDir(#[from] RunDirError),
    #[error("evaluation failed: {0}")]
    Evaluate(BoxError),
}

/// Everything the coordinator owns.
pub struct Coordinator {
    pub config: RunConfig,
    pub events: mpsc::Receiver<Event>,
    pub cancel: CancellationToken,
    /// Locked only by the coordinator's own blocking jobs (aggregation runs off the async runtime).
    pub strategy: Arc<Mutex<Box<dyn Strategy>>>,
    pub evaluator: Arc<Mutex<Box<dyn Evaluator + Send>>>,
    pub exporters: Arc<Vec<Box<dyn ModelExporter>>>,
    pub run_dir: RunDir,
    pub global: Arc<NamedTensors>,
    /// The last completed round; `None` for a fresh run (round 0, the initial evaluation, is still to do).
    pub completed: Option<u64>,
    pub model_tx: watch::Sender<Arc<PublishedModel>>,
    pub status_tx: watch::Sender<RunStatus>,
    pub controls: Controls,
    pub observer: Arc<dyn RunObserver>,
    /// Upload rights of the clients asked for rollout videos.
    pub sessions: Sessions,
    /// The statistics every client, the evaluator and the exporters normalise with: the dataset's, or those the
    /// run agreed by federated statistics (`None` until then).
    pub norm_stats: Option<NormalizationStats>,
    /// The dataset's statistics (`None` for a workload without any).
    pub dataset_stats: Option<NormalizationStats>,
    /// The blocking jobs in flight (aggregation, evaluation, file writes): aborting the coordinator does not stop
    /// one, so a server killed in a test waits for them, and nothing it started writes into the run directory
    /// after it (where a restarted server would be sweeping).
    pub jobs: TaskTracker,
}

pub(super) struct ClientEntry {
    pub(super) name: String,
    pub(super) public_key: String,
    pub(super) data: Option<DataSource>,
    pub(super) report: Option<Box<DataReport>>,
    pub(super) outbox: mpsc::UnboundedSender<ServerMessage>,
}

impl Coordinator {
    /// The model version clients train from: the last completed round.
    pub(super) fn global_version(&self) -> u64 {
        self.completed.unwrap_or(0)
    }
}

pub(super) struct Running {
    pub(super) c: Coordinator,
    pub(super) clients: BTreeMap<u64, ClientEntry>,
    /// Refusals since the last metrics line.
    pub(super) round_rejections: BTreeMap<ErrorCode, u64>,
    /// The norm screen, with the norms of the last aggregated round's accepted updates.
    pub(super) screen: NormScreen,
}

/// Runs `f` on tokio's blocking pool (aggregation, evaluation, file writes) as one of `jobs`, passing its panic on.
pub(super) async fn blocking<T: Send + 'static>(jobs: &TaskTracker, f: impl FnOnce() -> T + Send + 'static) -> T {
    match jobs.spawn_blocking(f).await {
        Ok(out) => out,
        Err(e) => std::panic::resume_unwind(e.into_panic()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_current_and_the_previous_model_are_served_and_no_older_one() {
        let first = PublishedModel::first(3, Bytes::from_static(b"three"));
        assert_eq!(first.bytes_of(3).map(|b| &b[..]), Some(&b"three"[..]));
        assert!(first.bytes_of(2).is_none());
        let second = first.next(4, Bytes::from_static(b"four"), None);
        let third = second.next(5, Bytes::from_static(b"five"), None);
        assert_eq!(third.bytes_of(5).map(|b| &b[..]), Some(&b"five"[..]));
        assert_eq!(third.bytes_of(4).map(|b| &b[..]), Some(&b"four"[..]));
        assert!(third.bytes_of(3).is_none() && third.bytes_of(6).is_none());
        // Round 0's model, published at start and again once evaluated, is held once.
        let republished = first.next(3, Bytes::from_static(b"three"), None);
        assert!(republished.bytes_of(3).is_some() && republished.previous.is_none());
    }

    /// Deltas are kept while their chain is shorter than the model, served for any version kept, and a version
    /// reached without one breaks every chain across it.
    #[test]
    fn deltas_are_kept_while_their_chain_is_shorter_than_the_model() {
        let model = Bytes::from(vec![0u8; 100]);
        let delta = |b: u8| Some(Bytes::from(vec![b; 20]));
        let mut published = PublishedModel::first(0, model.clone());
        assert_eq!(published.deltas_since(), None);
        for version in 1..=4 {
            published = published.next(version, model.clone(), delta(version as u8));
        }
        // 16 + 3 x (8 + 20) = 100 is no shorter than the model: the last two rounds' deltas are kept.
        assert_eq!(published.deltas_since(), Some(2));
        let chain = published.deltas(4, 2).unwrap();
        assert_eq!(chain, encode_model_deltas(2, [&[3u8; 20][..], &[4u8; 20][..]].into_iter()));
        assert_eq!(published.deltas(4, 3).unwrap(), encode_model_deltas(3, [&[4u8; 20][..]].into_iter()));
        assert_eq!(published.deltas(3, 2).unwrap(), encode_model_deltas(2, [&[3u8; 20][..]].into_iter()));
        assert!(
            published.deltas(4, 1).is_none() && published.deltas(5, 3).is_none() && published.deltas(3, 3).is_none()
        );
        let unchanged = published.next(5, model.clone(), None);
        assert_eq!(unchanged.deltas_since(), None);
        assert!(unchanged.deltas(4, 3).is_none());
        let again = unchanged.next(6, model.clone(), delta(6));
        assert_eq!(again.deltas_since(), Some(5));
        let too_long = again.next(7, model, Some(Bytes::from(vec![7u8; 90])));
        assert_eq!(too_long.deltas_since(), None, "a delta as long as the model is not served");
    }
}
