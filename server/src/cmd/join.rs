//! `fedvla join URL`: a native volunteer. It downloads what the server offers (`GET /api/volunteer`: its shard,
//! the policy configuration and the frozen weights), then runs the shared round loop
//! (`fedvla_server::native_client::volunteer`).

use std::path::PathBuf;

use fedvla_federation::{ClientError, ClientEvent, ErrorCode};
use fedvla_server::native_client;
use tracing_subscriber::filter::LevelFilter;

#[derive(clap::Args)]
pub struct Args {
    /// Server address: ws://host:port or http://host:port, or over TLS wss://host:port or https://host:port.
    url: String,
    /// A TLS server's certificate (PEM) to trust besides the Mozilla roots: a server with a self-signed one.
    #[arg(long)]
    ca_cert: Option<PathBuf>,
    /// Name shown to the server; the same name gets the same shard back after a restart (defaults to a random
    /// native-XXXXXX).
    #[arg(long)]
    name: Option<String>,
    /// Train on this shard instead of the one the server assigns.
    #[arg(long)]
    shard: Option<u32>,
    /// Token required by a server started with auth-token set.
    #[arg(long)]
    auth_token: Option<String>,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    super::support::init_tracing(None, LevelFilter::INFO);
    let name = args.name.unwrap_or_else(|| format!("native-{}", &fedvla_aggregator::sessions::random_token()[..6]));
    let result = super::support::runtime()?.block_on(native_client::volunteer(
        &args.url,
        args.ca_cert.as_deref(),
        &name,
        args.shard,
        args.auth_token,
        None,
        |event| match event {
            ClientEvent::Trained { round, examples, train_loss } => {
                tracing::info!(round, examples, train_loss, "trained");
            }
            ClientEvent::Refused { code, message } => {
                tracing::warn!(code = code.as_str(), %message, "refused");
            }
            other => tracing::info!(?other),
        },
    ));
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
