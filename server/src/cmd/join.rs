//! `fedvla join URL`: a native volunteer. It proves its key pair (kept under the user's config directory, one per
//! name), is admitted with its setup (its shard, the policy configuration, where the frozen weights are), downloads
//! them with its session, then runs the shared round loop (`fedvla_server::native_client::volunteer`). With `--dataset PATH` it trains on a LeRobot dataset of its own
//! instead of a shard: the dataset stays on this machine; only updates, metrics and the dataset's signature,
//! size and moments go to the server.

use std::path::PathBuf;

use fedvla_aggregator::config::ComputeDevice;
use fedvla_federation::{ClientError, ClientEvent, ErrorCode};
use fedvla_server::native_client::{self, Volunteer, VolunteerData};
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// Server address: ws://host:port or http://host:port, or over TLS wss://host:port or https://host:port.
    url: String,
    /// A TLS server's certificate (PEM) to trust besides the Mozilla roots: a server with a self-signed one.
    #[arg(long)]
    ca_cert: Option<PathBuf>,
    /// Name shown to the server, owned by this machine's key for it (`~/.config/fedvla/keys/NAME.key`, made on
    /// first use); the key gets the same shard back after a restart (defaults to a random native-XXXXXX).
    #[arg(long)]
    name: Option<String>,
    /// Train on this shard instead of the one the server assigns (refused when another volunteer's key holds it).
    #[arg(long, conflicts_with = "dataset")]
    shard: Option<u32>,
    /// Train on this LeRobot dataset (v3.0 or v2.1) of your own instead of a server shard; it never leaves this
    /// machine. The server refuses one that does not fit its run, naming what differs.
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Token required by a server started with auth-token set.
    #[arg(long)]
    auth_token: Option<String>,
    /// Where the training steps run: cpu, or wgpu (a GPU; needs a fedvla built with `--features gpu`).
    #[arg(long, default_value = "cpu")]
    device: ComputeDevice,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    super::support::init_tracing(None, LevelFilter::INFO);
    let name = args.name.unwrap_or_else(|| format!("native-{}", &fedvla_aggregator::sessions::random_token()[..6]));
    let data = match &args.dataset {
        Some(path) => VolunteerData::Own(path),
        None => VolunteerData::Shard(args.shard),
    };
    let (identity, key_file) = native_client::stored_identity(&name).map_err(super::support::boxed)?;
    // What an operator of a closed federation adds to its allow-list (`allowed-keys`).
    tracing::info!(%name, public_key = %identity.public_key_hex(), key_file = %key_file.display(), "volunteer key");
    let volunteer = Volunteer {
        server: &args.url,
        ca_cert: args.ca_cert.as_deref(),
        name: &name,
        identity: &identity,
        data,
        auth_token: args.auth_token,
        attack: None,
        device: args.device,
    };
    let result = super::support::runtime()?.block_on(native_client::volunteer(volunteer, |event| match event {
        ClientEvent::Trained { round, examples, train_loss } => {
            tracing::info!(round, examples, train_loss, "trained");
        }
        ClientEvent::Refused { code, message } => {
            tracing::warn!(code = code.as_str(), %message, "refused");
        }
        other => tracing::info!(?other),
    }));
    let summary = match result {
        Err(e) if matches!(e.downcast_ref(), Some(ClientError::Refused { code: ErrorCode::ShuttingDown, .. })) => {
            tracing::info!("the server shut down before the run finished");
            return Ok(());
        }
        other => other.map_err(super::support::boxed)?,
    };
    tracing::info!(
        rounds = summary.rounds_trained,
        bytes_up = summary.bytes_up,
        bytes_down = summary.bytes_down,
        "run finished"
    );
    Ok(())
}
