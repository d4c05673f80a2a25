//! The federation's HTTP/WebSocket app over the aggregator (`fedvla-aggregator`): `app(state) -> Router` with
//! the federation WebSocket ([`connection`]), the volunteers' downloads and uploads ([`volunteer`]), the
//! operator console ([`console`]) and, for every other path, the pages under `www-dir` ([`static_files`]);
//! the listener that serves it under bounds ([`http`]; [`bounds`] for what connections send), over TLS where the
//! run has a certificate ([`tls`]); and starting a whole server ([`server`]).

pub mod auth;
pub mod bounds;
pub mod connection;
pub mod console;
pub mod error;
pub mod http;
pub mod server;
pub mod state;
pub mod static_files;
pub mod tls;
pub mod volunteer;

use std::net::SocketAddr;

use axum::Router;
use axum::extract::ws::WebSocketUpgrade;
use axum::extract::{ConnectInfo, State};
use axum::response::Response;
use axum::routing::get;
use fedvla_federation::routes;
use futures_util::StreamExt;

use crate::connection::handle_socket;
use crate::state::{AppState, SocketState};

pub fn app(state: AppState) -> Router {
    Router::new()
        .route(routes::WS, get(ws_upgrade))
        .merge(volunteer::routes())
        .merge(console::api::routes(&state.console.hub))
        .fallback(static_files::serve)
        .with_state(state)
}

async fn ws_upgrade(
    ws: WebSocketUpgrade,
    State(state): State<SocketState>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
) -> Response {
    // Twice our frame limit at the WebSocket layer, so a moderately oversized frame still reaches the codec and
    // gets a clear error, while an absurd one is cut off before it is buffered.
    let limit = state.limits.max_frame_bytes * 2 + 64 * 1024;
    let sockets = state.sockets.clone();
    ws.max_frame_size(limit).max_message_size(limit).on_upgrade(move |socket| {
        let (sink, stream) = socket.split();
        sockets.track_future(handle_socket(sink, stream, state, peer.ip()))
    })
}
