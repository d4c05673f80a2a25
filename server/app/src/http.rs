//! The HTTP listener: serves the app on every accepted connection (with upgrades, for the WebSocket) under the
//! bounds a server that strangers connect to needs. At most `max-connections` sockets are open at once (one more
//! is closed as soon as it is accepted, and counted); a request head must arrive whole within
//! `header-read-timeout-ms` (with TLS, the handshake too); a socket on which nothing moves either way for
//! `idle-timeout-ms` is closed (the WebSocket pings idle volunteers well within that, see
//! [`HttpLimits::keepalive`]).

use std::io;
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll, ready};
use std::time::Duration;

use axum::Router;
use axum::extract::ConnectInfo;
use axum::http::Request;
use hyper::body::Incoming;
use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tokio_rustls::TlsAcceptor;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use tower::ServiceExt;

use crate::console::ConsoleHub;

/// How long open connections get to finish their requests once the server shuts down.
pub(crate) const SHUTDOWN_GRACE: Duration = Duration::from_secs(5);

/// The listener's bounds (run configuration keys `max-connections`, `header-read-timeout-ms`, `idle-timeout-ms`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HttpLimits {
    pub max_connections: usize,
    pub header_read_timeout: Duration,
    pub idle_timeout: Duration,
}

impl HttpLimits {
    /// How often the server pings an idle WebSocket: often enough that proxies keep it open (20 s) and that the
    /// idle timeout never closes a volunteer waiting for its next round.
    pub fn keepalive(&self) -> Duration {
        (self.idle_timeout / 3).min(Duration::from_secs(20))
    }
}

/// Accepts connections on `listener` and serves `app` on each until `shutdown` (over TLS with `tls`), then gives
/// open requests [`SHUTDOWN_GRACE`] to finish. Refused connections are counted on the console.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: HttpLimits,
    tls: Option<TlsAcceptor>,
    console: ConsoleHub,
    shutdown: CancellationToken,
) -> io::Result<()> {
    let permits = Arc::new(Semaphore::new(limits.max_connections));
    let mut builder = http1::Builder::new();
    builder.timer(TokioTimer::new()).header_read_timeout(limits.header_read_timeout);
    let connections = TaskTracker::new();
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = shutdown.cancelled() => break,
        };
        let (stream, peer) = match accepted {
            Ok(accepted) => accepted,
            Err(e) => {
                // Out of file descriptors and the like: wait a little instead of spinning.
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(permit) = Arc::clone(&permits).try_acquire_owned() else {
            console.count_refused_connection();
            tracing::debug!(%peer, max = limits.max_connections, "connection refused: too many open");
            continue;
        };
        if let Err(e) = stream.set_nodelay(true) {
            tracing::debug!(error = %e, "TCP_NODELAY not set");
        }
        let stream = Watched::new(stream, limits.idle_timeout, permit);
        let (builder, app, tls, shutdown) = (builder.clone(), app.clone(), tls.clone(), shutdown.clone());
        connections.spawn(async move {
            let result = match tls {
                None => serve_connection(&builder, stream, app, peer, &shutdown).await,
                Some(acceptor) => {
                    let handshake = tokio::time::timeout(limits.header_read_timeout, acceptor.accept(stream));
                    match handshake.await {
                        Ok(Ok(stream)) => serve_connection(&builder, stream, app, peer, &shutdown).await,
                        Ok(Err(e)) => {
                            tracing::debug!(%peer, error = %e, "TLS handshake failed");
                            return;
                        }
                        Err(_) => {
                            tracing::debug!(%peer, "TLS handshake timed out");
                            return;
                        }
                    }
                }
            };
            if let Err(e) = result {
                tracing::debug!(%peer, error = %e, "connection ended");
            }
        });
    }
    connections.close();
    if tokio::time::timeout(SHUTDOWN_GRACE, connections.wait()).await.is_err() {
        tracing::info!("closing connections still open after {SHUTDOWN_GRACE:?}");
    }
    Ok(())
}

/// Serves `app` on one connection from `peer` (with upgrades, for the WebSocket) until it ends, or gracefully
/// after `shutdown`. Every request carries the peer's address as axum's [`ConnectInfo`] (joins are counted by it).
async fn serve_connection<S>(
    builder: &http1::Builder,
    stream: S,
    app: Router,
    peer: SocketAddr,
    shutdown: &CancellationToken,
) -> Result<(), hyper::Error>
where
    S: AsyncRead + AsyncWrite + Unpin + Send + 'static,
{
    let app = app.map_request(move |mut request: Request<Incoming>| {
        request.extensions_mut().insert(ConnectInfo(peer));
        request
    });
    let conn = builder.serve_connection(TokioIo::new(stream), TowerToHyperService::new(app)).with_upgrades();
    let mut conn = std::pin::pin!(conn);
    tokio::select! {
        result = conn.as_mut() => result,
        () = shutdown.cancelled() => {
            conn.as_mut().graceful_shutdown();
            conn.await
        }
    }
}

/// A TCP stream that fails with `TimedOut` once nothing has been read or written for `idle`, and holds its place
/// under the connection cap for as long as it lives (an upgraded WebSocket included).
struct Watched {
    stream: TcpStream,
    idle: Duration,
    last_activity: Instant,
    deadline: Pin<Box<Sleep>>,
    _permit: OwnedSemaphorePermit,
}

impl Watched {
    fn new(stream: TcpStream, idle: Duration, permit: OwnedSemaphorePermit) -> Self {
        let now = Instant::now();
        Self {
            stream,
            idle,
            last_activity: now,
            deadline: Box::pin(tokio::time::sleep_until(now + idle)),
            _permit: permit,
        }
    }

    /// Pending until the socket has been idle for `idle`; the timer is moved on lazily, only when it fires.
    fn poll_idle(&mut self, cx: &mut Context<'_>) -> Poll<io::Error> {
        loop {
            ready!(self.deadline.as_mut().poll(cx));
            let due = self.last_activity + self.idle;
            if Instant::now() >= due {
                return Poll::Ready(io::Error::new(io::ErrorKind::TimedOut, format!("idle for {:?}", self.idle)));
            }
            self.deadline.as_mut().reset(due);
        }
    }
}

impl AsyncRead for Watched {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let before = buf.filled().len();
        match Pin::new(&mut self.stream).poll_read(cx, buf) {
            Poll::Ready(result) => {
                if buf.filled().len() > before {
                    self.last_activity = Instant::now();
                }
                Poll::Ready(result)
            }
            Poll::Pending => self.poll_idle(cx).map(Err),
        }
    }
}

impl AsyncWrite for Watched {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, data: &[u8]) -> Poll<io::Result<usize>> {
        let written = ready!(Pin::new(&mut self.stream).poll_write(cx, data));
        if matches!(written, Ok(n) if n > 0) {
            self.last_activity = Instant::now();
        }
        Poll::Ready(written)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}
