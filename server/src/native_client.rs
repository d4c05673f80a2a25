//! The native client transport: tokio-tungstenite for the WebSocket, a plain HTTP/1.1 GET (hyper) for models.

use std::time::Instant;

use burn::tensor::Device;
use fedvla_data::ShardFileManifest;
use fedvla_data::shard::verify_shard_bytes;
use fedvla_federation::{BoxError, ClientTransport, Video, VolunteerSetup};
use fedvla_learner::SmolVlaTrainer;
use fedvla_learner::volunteer::{Downloads, volunteer_trainer};
use futures_util::{SinkExt, StreamExt};
use http_body_util::{BodyExt, Full};
use hyper::body::Bytes;
use hyper_util::rt::TokioIo;
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::http::Uri;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

/// One request over a fresh HTTP/1 connection to `authority`; a non-2xx status is an error carrying the body.
pub async fn http_request(
    authority: &str,
    request: hyper::http::request::Builder,
    body: Bytes,
) -> Result<Vec<u8>, BoxError> {
    let stream = TcpStream::connect(authority).await?;
    let (mut sender, conn) = hyper::client::conn::http1::handshake(TokioIo::new(stream)).await?;
    let conn = tokio::spawn(conn);
    let request = request.header(hyper::header::HOST, authority).body(Full::new(body))?;
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

/// A native SmolVLA volunteer: downloads what `setup` points at (frozen weights, global model, shard) and builds
/// its trainer on the CPU, as the browser does in wasm.
pub async fn smolvla_volunteer(
    transport: &NativeTransport,
    setup: &VolunteerSetup,
    name: &str,
) -> Result<SmolVlaTrainer, BoxError> {
    let frozen_url = setup.frozen_url.as_deref().ok_or("the server offers no frozen weights")?;
    let frozen = transport.get(frozen_url).await?;
    let global = transport.get(&format!("/model/{}", setup.model_version)).await?;
    let (manifest, shard) = transport.fetch_shard(setup.shard_index as usize).await?;
    tracing::info!(frozen_bytes = frozen.len(), shard_bytes = shard.len(), "downloaded");
    let downloads = Downloads { setup, frozen: &frozen, global: &global, shard: &shard, manifest: &manifest };
    volunteer_trainer(&downloads, name, &Device::flex().autodiff(), "cpu-flex")
}

pub struct NativeTransport {
    ws: WebSocketStream<MaybeTlsStream<TcpStream>>,
    authority: String,
    started: Instant,
}

impl NativeTransport {
    /// `GET path` on the server.
    pub async fn get(&self, path: &str) -> Result<Vec<u8>, BoxError> {
        http_request(&self.authority, hyper::Request::get(path), Bytes::new()).await
    }

    /// What the server offers volunteer `name` (`GET /api/volunteer?name=`): a new name gets the next shard
    /// round-robin, a returning one its shard again; `shard` asks for that one (it becomes the name's).
    pub async fn fetch_setup(&self, name: &str, shard: Option<u32>) -> Result<VolunteerSetup, BoxError> {
        let name = percent_encoding::utf8_percent_encode(name, percent_encoding::NON_ALPHANUMERIC);
        let shard = shard.map(|s| format!("&shard={s}")).unwrap_or_default();
        let bytes = self.get(&format!("/api/volunteer?name={name}{shard}")).await?;
        serde_json::from_slice(&bytes).map_err(|e| format!("GET /api/volunteer: {e}").into())
    }

    /// Downloads shard `index` and checks it against its manifest (size and SHA-256) before use.
    pub async fn fetch_shard(&self, index: usize) -> Result<(ShardFileManifest, Vec<u8>), BoxError> {
        let manifest: ShardFileManifest =
            serde_json::from_slice(&self.get(&format!("/shard/{index}/manifest")).await?)?;
        let bytes = self.get(&format!("/shard/{index}")).await?;
        verify_shard_bytes(std::path::Path::new(&manifest.file), &bytes, &manifest)?;
        Ok((manifest, bytes))
    }

    /// Connects to a server given as `ws://host:port`, `http://host:port` or `host:port` (path ignored).
    pub async fn connect(server: &str) -> Result<Self, BoxError> {
        let uri: Uri = if server.contains("://") { server.parse()? } else { format!("ws://{server}").parse()? };
        if !matches!(uri.scheme_str(), Some("ws" | "http")) {
            return Err(
                format!("unsupported scheme in `{server}`: use ws:// or http:// (TLS is left to a proxy)").into()
            );
        }
        let authority = uri.authority().ok_or_else(|| format!("no host in `{server}`"))?.to_string();
        // Nagle off: an update is a small header message followed at once by frames.
        let (ws, _) = tokio_tungstenite::connect_async_with_config(format!("ws://{authority}/ws"), None, true).await?;
        Ok(Self { ws, authority, started: Instant::now() })
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

    async fn fetch_model(&mut self, version: u64) -> Result<Vec<u8>, BoxError> {
        self.get(&format!("/model/{version}")).await
    }

    async fn upload_video(&mut self, round: u64, session: &str, video: Video) -> Result<(), BoxError> {
        let request = hyper::Request::post(format!("/rollout/{round}/{}", video.file_name))
            .header(hyper::header::AUTHORIZATION, format!("Bearer {session}"))
            .header(hyper::header::CONTENT_TYPE, video.mime);
        http_request(&self.authority, request, Bytes::from(video.bytes)).await.map(drop)
    }

    fn now_seconds(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }
}
