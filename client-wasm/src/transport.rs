//! The browser's `ClientTransport`: the federation WebSocket through gloo-net, models and uploads through fetch.

use fedvla_federation::{BoxError, ClientTransport, Video, routes};
use futures_util::stream::{SplitSink, SplitStream};
use futures_util::{SinkExt, StreamExt};
use gloo_net::websocket::Message;
use gloo_net::websocket::futures::WebSocket;

use crate::browser::now_seconds;
use crate::download::fetch_with_progress;

pub struct BrowserTransport {
    sink: SplitSink<WebSocket, Message>,
    stream: SplitStream<WebSocket>,
    /// e.g. "http://127.0.0.1:8080"; HTTP paths are relative to it.
    origin: String,
}

impl BrowserTransport {
    /// Opens `ws(s)://<host>/ws` of the server at `origin` (http or https).
    pub fn connect(origin: &str) -> Result<Self, BoxError> {
        let ws_url = match origin.split_once("://") {
            Some(("https", rest)) => format!("wss://{rest}{}", routes::WS),
            Some(("http", rest)) => format!("ws://{rest}{}", routes::WS),
            _ => return Err(format!("server origin {origin:?} is not http(s)://host:port").into()),
        };
        let socket = WebSocket::open(&ws_url).map_err(|e| format!("opening {ws_url}: {e}"))?;
        let (sink, stream) = socket.split();
        Ok(Self { sink, stream, origin: origin.trim_end_matches('/').to_owned() })
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.origin)
    }
}

impl ClientTransport for BrowserTransport {
    async fn send_text(&mut self, text: String) -> Result<(), BoxError> {
        self.sink.send(Message::Text(text)).await.map_err(|e| e.to_string().into())
    }

    async fn send_binary(&mut self, frame: Vec<u8>) -> Result<(), BoxError> {
        self.sink.send(Message::Bytes(frame)).await.map_err(|e| e.to_string().into())
    }

    async fn recv_text(&mut self) -> Result<Option<String>, BoxError> {
        match self.stream.next().await {
            Some(Ok(Message::Text(text))) => Ok(Some(text)),
            Some(Ok(Message::Bytes(_))) => Err("the server sent an unexpected binary frame".into()),
            // gloo-net reports a closed socket as an error; both mean the connection is over.
            Some(Err(gloo_net::websocket::WebSocketError::ConnectionClose(_))) | None => Ok(None),
            Some(Err(e)) => Err(e.to_string().into()),
        }
    }

    async fn fetch_model(&mut self, version: u64, session: &str) -> Result<Vec<u8>, BoxError> {
        let url = self.url(&routes::model(version));
        fetch_with_progress(&url, session, |_, _| {}).await.map_err(|e| format!("{e:?}").into())
    }

    async fn fetch_model_deltas(&mut self, version: u64, from: u64, session: &str) -> Result<Vec<u8>, BoxError> {
        let url = self.url(&routes::model_deltas(version, from));
        fetch_with_progress(&url, session, |_, _| {}).await.map_err(|e| format!("{e:?}").into())
    }

    async fn fetch_correction(&mut self, round: u64, session: &str) -> Result<Vec<u8>, BoxError> {
        let url = self.url(&routes::correction(round));
        let request = gloo_net::http::Request::get(&url)
            .header("authorization", &format!("Bearer {session}"))
            .build()
            .map_err(|e| e.to_string())?;
        let what = format!("GET {url}");
        let response = send_checked(request, &what).await?;
        response.binary().await.map_err(|e| format!("{what}: {e}").into())
    }

    async fn upload_video(&mut self, round: u64, session: &str, video: Video) -> Result<(), BoxError> {
        let url = self.url(&routes::rollout_video(round, &video.file_name));
        let body = js_sys::Uint8Array::from(video.bytes.as_slice());
        let request = gloo_net::http::Request::post(&url)
            .header("authorization", &format!("Bearer {session}"))
            .header("content-type", &video.mime)
            .body(body)
            .map_err(|e| e.to_string())?;
        send_checked(request, &format!("POST {url}")).await.map(drop)
    }

    fn now_seconds(&self) -> f64 {
        now_seconds()
    }
}

/// Sends `request`; a failure or an answer other than 2xx is an error naming `what` (method and URL), with the
/// status and the server's message.
async fn send_checked(request: gloo_net::http::Request, what: &str) -> Result<gloo_net::http::Response, BoxError> {
    let response = request.send().await.map_err(|e| format!("{what}: {e}"))?;
    if !response.ok() {
        return Err(format!("{what}: {} {}", response.status(), response.text().await.unwrap_or_default()).into());
    }
    Ok(response)
}
