//! The native volunteer: its I/O (tokio-tungstenite for the WebSocket, HTTP/1.1 requests with hyper for the
//! shared start-up's downloads ([`Fetch`]) and its uploads, each over TCP or, for `https://` and `wss://`
//! servers, TLS ([`Dialer`]); its key pair, kept in a file under the user's config directory
//! ([`stored_identity`])) and [`volunteer`], what `fedvla join` and every client of `fedvla simulate` run: the
//! same identity handshake, downloads and round loop as the browser's, on a server shard or on the volunteer's own
//! dataset.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use fedvla_aggregator::config::{AttackKind, ComputeDevice, Partitioning};
use fedvla_federation::identity::SEED_BYTES;
use fedvla_federation::{
    Admission, BoxError, ClientEvent, ClientOptions, ClientSummary, ClientTransport, Identity, Introduction,
    LocalTrainer, OwnDataset, Video, WorkloadKind, fnv1a, identify, routes, run_client,
};
use fedvla_learner::feature_cache::DEFAULT_SPILL_BYTES;
use fedvla_learner::own_data::{OwnShard, check_fits_run, pack_own_dataset};
use fedvla_learner::volunteer::{
    Fetch, fetch_tokenizer, policy_config, smolvla_volunteer, smolvla_volunteer_on, volunteer_seed,
};
use fedvla_workloads::device::training_device;
use fedvla_workloads::linreg::LinRegTrainer;
use fedvla_workloads::sim_eval::FilmedRollouts;

use crate::attack::{Attack, Attacker};
use futures_util::{SinkExt, StreamExt};
use http_body_util::{BodyExt, Full};
use hyper::body::Bytes;
use hyper_util::rt::TokioIo;
use tokio::net::TcpStream;
use tokio_rustls::TlsConnector;
use tokio_rustls::client::TlsStream;
use tokio_rustls::rustls::pki_types::ServerName;
use tokio_rustls::rustls::{self, ClientConfig, RootCertStore};
use tokio_tungstenite::WebSocketStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::http::Uri;
use tokio_util::either::Either;

/// A connection to the server: plain TCP, or TLS over it.
pub type Connection = Either<TcpStream, TlsStream<TcpStream>>;

/// How a native volunteer reaches the server: its `host:port`, and for a TLS server (`https://`, `wss://`) the
/// name its certificate must carry and the roots it must chain to: the Mozilla roots (webpki-roots) and any
/// given with `--ca-cert` (a server's own self-signed certificate, say).
#[derive(Clone)]
pub struct Dialer {
    authority: String,
    tls: Option<(TlsConnector, ServerName<'static>)>,
}

impl Dialer {
    /// Plain TCP to `authority` (`host:port`).
    pub fn plain(authority: &str) -> Self {
        Self { authority: authority.to_owned(), tls: None }
    }

    /// TLS to `authority`, whose certificate must name `host` and chain to the Mozilla roots or to a certificate
    /// of the PEM file `extra_roots`.
    pub fn tls(authority: &str, host: &str, extra_roots: Option<&Path>) -> Result<Self, BoxError> {
        let mut roots = RootCertStore::from_iter(webpki_roots::TLS_SERVER_ROOTS.iter().cloned());
        if let Some(path) = extra_roots {
            for certificate in fedvla_app::tls::certificates(path)? {
                roots.add(certificate).map_err(|e| format!("{}: {e}", path.display()))?;
            }
        }
        let config = ClientConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
            .with_safe_default_protocol_versions()?
            .with_root_certificates(roots)
            .with_no_client_auth();
        let name = ServerName::try_from(host.to_owned()).map_err(|e| format!("server name `{host}`: {e}"))?;
        Ok(Self { authority: authority.to_owned(), tls: Some((TlsConnector::from(Arc::new(config)), name)) })
    }

    /// Whether its connections are TLS.
    pub fn is_tls(&self) -> bool {
        self.tls.is_some()
    }

    /// A fresh connection, Nagle off (an update is a small header message followed at once by frames).
    pub async fn connect(&self) -> Result<Connection, BoxError> {
        let stream = TcpStream::connect(&self.authority).await?;
        stream.set_nodelay(true)?;
        Ok(match &self.tls {
            None => Either::Left(stream),
            Some((connector, name)) => Either::Right(connector.connect(name.clone(), stream).await?),
        })
    }
}

/// One request over a fresh HTTP/1 connection by `dialer`; a non-2xx status is an error carrying the body.
pub async fn http_request(
    dialer: &Dialer,
    request: hyper::http::request::Builder,
    body: Bytes,
) -> Result<Vec<u8>, BoxError> {
    let stream = dialer.connect().await?;
    let (mut sender, conn) = hyper::client::conn::http1::handshake(TokioIo::new(stream)).await?;
    let conn = tokio::spawn(conn);
    let request = request.header(hyper::header::HOST, &dialer.authority).body(Full::new(body))?;
    let what = format!("{} {}", request.method(), request.uri());
    let response = sender.send_request(request).await?;
    let status = response.status();
    let body = response.into_body().collect().await?.to_bytes();
    drop(sender);
    conn.await??;
    if !status.is_success() {
        return Err(format!("{what}: {status}: {}", String::from_utf8_lossy(&body)).into());
    }
    Ok(body.to_vec())
}

pub struct NativeTransport {
    ws: WebSocketStream<Connection>,
    dialer: Dialer,
    /// The admission's session, presented with every download of the start-up.
    session: Option<String>,
    started: Instant,
}

impl NativeTransport {
    /// `GET path` on the server.
    pub async fn get(&self, path: &str) -> Result<Vec<u8>, BoxError> {
        Fetch::get(self, path, path, None).await
    }

    /// Connects to a server given as `ws://host:port`, `http://host:port` or `host:port` (path ignored), or over
    /// TLS as `wss://` or `https://`, trusting the Mozilla roots.
    pub async fn connect(server: &str) -> Result<Self, BoxError> {
        Self::connect_trusting(server, None).await
    }

    /// As [`NativeTransport::connect`], a TLS server's certificate chaining to the Mozilla roots or to one in the
    /// PEM file `extra_roots`.
    pub async fn connect_trusting(server: &str, extra_roots: Option<&Path>) -> Result<Self, BoxError> {
        let uri: Uri = if server.contains("://") { server.parse()? } else { format!("ws://{server}").parse()? };
        let authority = uri.authority().ok_or_else(|| format!("no host in `{server}`"))?;
        let dialer = match uri.scheme_str() {
            Some("ws" | "http") => Dialer::plain(authority.as_str()),
            Some("wss" | "https") => Dialer::tls(authority.as_str(), authority.host(), extra_roots)?,
            _ => return Err(format!("unsupported scheme in `{server}`: use ws://, http://, wss:// or https://").into()),
        };
        let scheme = if dialer.is_tls() { "wss" } else { "ws" };
        let url = format!("{scheme}://{authority}{}", routes::WS);
        let (ws, _) = tokio_tungstenite::client_async_with_config(url, dialer.connect().await?, None).await?;
        Ok(Self { ws, dialer, session: None, started: Instant::now() })
    }

    /// Presents `session` (the admission's) with every download of the start-up.
    pub fn with_session(mut self, session: &str) -> Self {
        self.session = Some(session.to_owned());
        self
    }

    /// `GET path` presenting `session`.
    async fn get_with(&self, path: &str, session: &str) -> Result<Vec<u8>, BoxError> {
        let request = hyper::Request::get(path).header(hyper::header::AUTHORIZATION, format!("Bearer {session}"));
        http_request(&self.dialer, request, Bytes::new()).await
    }
}

impl Fetch for NativeTransport {
    async fn get(&self, path: &str, what: &str, _cache_key: Option<&str>) -> Result<Vec<u8>, BoxError> {
        let session = self.session.as_deref().ok_or("no session yet: identify before downloading")?;
        let bytes = self.get_with(path, session).await?;
        tracing::debug!(what, bytes = bytes.len(), "downloaded");
        Ok(bytes)
    }
}

impl ClientTransport for NativeTransport {
    async fn send_text(&mut self, text: String) -> Result<(), BoxError> {
        Ok(self.ws.send(Message::text(text)).await?)
    }

    async fn send_binary(&mut self, frame: Vec<u8>) -> Result<(), BoxError> {
        Ok(self.ws.send(Message::binary(frame)).await?)
    }

    async fn recv_text(&mut self) -> Result<Option<String>, BoxError> {
        loop {
            match self.ws.next().await {
                Some(Ok(Message::Text(text))) => return Ok(Some(text.as_str().to_owned())),
                Some(Ok(Message::Close(_))) | None => return Ok(None),
                Some(Ok(Message::Binary(_))) => {
                    return Err("the server sent an unexpected binary frame".into());
                }
                Some(Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_))) => {}
                Some(Err(e)) => return Err(e.into()),
            }
        }
    }

    async fn fetch_model(&mut self, version: u64, session: &str) -> Result<Vec<u8>, BoxError> {
        self.get_with(&routes::model(version), session).await
    }

    async fn fetch_model_deltas(&mut self, version: u64, from: u64, session: &str) -> Result<Vec<u8>, BoxError> {
        self.get_with(&routes::model_deltas(version, from), session).await
    }

    async fn fetch_correction(&mut self, round: u64, session: &str) -> Result<Vec<u8>, BoxError> {
        self.get_with(&routes::correction(round), session).await
    }

    async fn upload_video(&mut self, round: u64, session: &str, video: Video) -> Result<(), BoxError> {
        let request = hyper::Request::post(routes::rollout_video(round, &video.file_name))
            .header(hyper::header::AUTHORIZATION, format!("Bearer {session}"))
            .header(hyper::header::CONTENT_TYPE, video.mime);
        http_request(&self.dialer, request, Bytes::from(video.bytes)).await.map(drop)
    }

    fn now_seconds(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }
}

/// What a volunteer trains on.
#[derive(Debug, Clone, Copy)]
pub enum VolunteerData<'a> {
    /// A shard the server serves: this one, or the one it assigns.
    Shard(Option<u32>),
    /// The LeRobot dataset at this path on the volunteer's machine; it never leaves it.
    Own(&'a Path),
}

/// A volunteer of the server at `server` (`ws://`, `http://`, `host:port`, or over TLS `wss://`, `https://`,
/// trusting the Mozilla roots and those of the PEM file `ca_cert`).
pub struct Volunteer<'a> {
    pub server: &'a str,
    pub ca_cert: Option<&'a Path>,
    pub name: &'a str,
    /// The key pair it proves on joining.
    pub identity: &'a Identity,
    pub data: VolunteerData<'a>,
    pub auth_token: Option<String>,
    /// Corrupts its updates (simulations only).
    pub attack: Option<Attack>,
    /// Where its training steps run.
    pub device: ComputeDevice,
}

/// `v` until the run finishes: proves its key and is admitted with its setup, builds the trainer the server's
/// workload needs from what it downloads with the admission's session (and, with its own dataset, from that),
/// and runs the shared round loop, reporting to `on_event`.
pub async fn volunteer(v: Volunteer<'_>, on_event: impl FnMut(ClientEvent)) -> Result<ClientSummary, BoxError> {
    let Volunteer { server, ca_cert, name, identity, data, auth_token, attack, device } = v;
    let intro = Introduction {
        name: name.to_owned(),
        auth_token,
        shard: match data {
            VolunteerData::Shard(shard) => shard,
            VolunteerData::Own(_) => None,
        },
        own_dataset: matches!(data, VolunteerData::Own(_)),
    };
    let (mut transport, Admission { client_id, session, setup }) = admitted(server, ca_cert, identity, &intro).await?;
    tracing::info!(
        client_id,
        workload = ?setup.workload,
        shard = setup.shard_index,
        of = setup.shard_count,
        "admitted"
    );
    let mut options = ClientOptions { session, data: None };
    match setup.workload {
        WorkloadKind::Linreg => {
            if let VolunteerData::Own(root) = data {
                return Err(format!("the server runs linreg, which takes no own dataset ({})", root.display()).into());
            }
            // The linreg shard is generated from its index; the setup says how the data is split.
            let partitioning: Partitioning = serde_json::from_value(setup.policy["partitioning"].clone())
                .map_err(|e| format!("the linreg setup's partitioning: {e}"))?;
            let mut trainer = LinRegTrainer::new(setup.shard_index as usize, partitioning);
            if poisons_labels(attack) {
                trainer.shuffle_labels(fnv1a(name));
            }
            run_as(&mut transport, trainer, attack, &options, on_event).await
        }
        WorkloadKind::Smolvla => {
            let (device, backend) = training_device(device)?;
            tracing::info!(backend, "training device");
            let (trainer, own) = match data {
                VolunteerData::Shard(_) => (smolvla_volunteer(&transport, &setup, name, &device, backend).await?, None),
                VolunteerData::Own(root) => {
                    let run = setup.dataset_signature.as_ref().ok_or("the server takes no own datasets")?;
                    let tokenizer = fetch_tokenizer(&transport, &setup).await?;
                    let cfg = policy_config(&setup)?;
                    let packed = pack_own_directory(root, run, &cfg, &tokenizer, volunteer_seed(name))?;
                    let trainer =
                        smolvla_volunteer_on(&transport, &setup, name, packed.shard, &device, backend).await?;
                    let train_examples = trainer.examples().train_examples();
                    tracing::info!(dataset = %root.display(), train_examples, "training on the volunteer's own dataset");
                    (trainer, Some(OwnDataset { signature: packed.signature, train_examples }))
                }
            };
            options.data = Some(trainer.examples().data_report(own));
            // The frozen weights are named by their content hash (the last segment of their URL).
            let frozen = setup.frozen_url.as_deref().and_then(|url| url.rsplit('/').next()).unwrap_or("unnamed");
            let mut trainer = trainer.spill_feature_cache(&feature_cache_dir(), frozen, DEFAULT_SPILL_BYTES);
            if poisons_labels(attack) {
                trainer.shuffle_labels(fnv1a(name));
            }
            run_as(&mut transport, FilmedRollouts(trainer), attack, &options, on_event).await
        }
    }
}

/// The LeRobot dataset at `root` packed for the run (see [`fedvla_learner::own_data`]): every episode, read where it
/// lies, refused before anything is decoded when it does not fit the run's signature `run`.
fn pack_own_directory(
    root: &Path,
    run: &fedvla_federation::DatasetSignature,
    cfg: &fedvla_policy::SmolVlaConfig,
    tokenizer: &fedvla_policy::Tokenizer,
    seed: u64,
) -> Result<OwnShard, BoxError> {
    let named = |e: &dyn std::fmt::Display| format!("own dataset {}: {e}", root.display());
    let dataset = fedvla_data::LeRobotDataset::open(root).map_err(|e| named(&e))?;
    let signature = check_fits_run(dataset.info(), run).map_err(|e| named(&e))?;
    let episodes: Vec<usize> = dataset.episodes().iter().map(|e| e.episode_index).collect();
    pack_own_dataset(&dataset, &episodes, signature, cfg, tokenizer, seed, &mut |episode| {
        tracing::debug!(episode = episode.episode_index, "own episode packed");
    })
}

/// Where native volunteers spill their frozen-feature caches: `$XDG_CACHE_HOME/fedvla/features`, or
/// `~/.cache/fedvla/features`, or the temporary directory.
fn feature_cache_dir() -> PathBuf {
    let base = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|home| PathBuf::from(home).join(".cache")))
        .unwrap_or_else(std::env::temp_dir);
    base.join("fedvla").join("features")
}

/// A connection to `server` (trusting `ca_cert` besides the Mozilla roots) on which `identity` proved itself as
/// `intro` says, and the admission; the transport presents the admission's session with every download.
pub async fn admitted(
    server: &str,
    ca_cert: Option<&Path>,
    identity: &Identity,
    intro: &Introduction,
) -> Result<(NativeTransport, Admission), BoxError> {
    let mut transport = NativeTransport::connect_trusting(server, ca_cert).await?;
    let admission = identify(&mut transport, identity, intro).await?;
    Ok((transport.with_session(&admission.session), admission))
}

/// Whether `attack` poisons the volunteer's data before it trains.
fn poisons_labels(attack: Option<Attack>) -> bool {
    attack.is_some_and(|a| a.kind == AttackKind::LabelShuffle)
}

/// The round loop with `trainer`, honest or, with `attack`, corrupting its updates.
async fn run_as(
    transport: &mut NativeTransport,
    mut trainer: impl LocalTrainer,
    attack: Option<Attack>,
    options: &ClientOptions,
    on_event: impl FnMut(ClientEvent),
) -> Result<ClientSummary, BoxError> {
    Ok(match attack {
        Some(attack) => run_client(transport, &mut Attacker::new(trainer, attack), options, on_event).await?,
        None => run_client(transport, &mut trainer, options, on_event).await?,
    })
}

/// The key pair of volunteer `name` on this machine: `fedvla/keys/<name>.key` under `$XDG_CONFIG_HOME` (or
/// `~/.config`), its secret seed in hex, readable by the user alone; made on first use. Copy the file to join as the
/// same volunteer from another machine.
pub fn stored_identity(name: &str) -> Result<(Identity, PathBuf), BoxError> {
    let config = match std::env::var_os("XDG_CONFIG_HOME").filter(|dir| !dir.is_empty()) {
        Some(dir) => PathBuf::from(dir),
        None => {
            PathBuf::from(std::env::var_os("HOME").ok_or("neither XDG_CONFIG_HOME nor HOME is set")?).join(".config")
        }
    };
    // Names may hold any printable character: the file name keeps the safe ones and escapes the others.
    let file: String = name
        .bytes()
        .map(|b| match b {
            b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'-' | b'_' => char::from(b).to_string(),
            other => format!("%{other:02X}"),
        })
        .collect();
    let path = config.join("fedvla").join("keys").join(format!("{file}.key"));
    let identity = match std::fs::read_to_string(&path) {
        Ok(text) => Identity::from_seed_hex(&text).map_err(|e| format!("{}: {e}", path.display()))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let identity = Identity::from_seed_hex(&fedvla_aggregator::sessions::random_hex::<SEED_BYTES>())?;
            write_private(&path, &identity.seed_hex()).map_err(|e| format!("{}: {e}", path.display()))?;
            identity
        }
        Err(e) => return Err(format!("{}: {e}", path.display()).into()),
    };
    Ok((identity, path))
}

/// Writes `text` to a new file only its owner may read (`create_new`: never over another key).
fn write_private(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file = options.open(path)?;
    writeln!(file, "{text}")?;
    file.sync_all()
}

/// A key pair derived from `name` alone, for `simulate`'s volunteers and tests: anyone who knows the name can make
/// it, so never for a real volunteer. The same name gets the same key, so a resumed simulation keeps its shards.
pub fn simulated_identity(name: &str) -> Identity {
    use rand::{Rng, SeedableRng};
    let seed: [u8; SEED_BYTES] = rand::rngs::StdRng::seed_from_u64(fnv1a(&format!("simulated {name}"))).random();
    Identity::from_seed(seed)
}
