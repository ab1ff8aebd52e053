//! The listener itself: hyper's HTTP/1 server on a single-threaded tokio runtime of its own,
//! with every resource a client can make it hold bounded.
//!
//! | limit | value | past it |
//! |---|---|---|
//! | connections open at once | [`MAX_CONNECTIONS`] | a short 503 written without waiting, then closed |
//! | `/events` streams | [`super::MAX_STREAMS`] | 503 |
//! | request head (request line and headers) | [`MAX_HEAD_BYTES`], [`MAX_HEADERS`] headers | 431, closed |
//! | time to send the head | [`HEAD_TIMEOUT`] | closed |
//! | a whole exchange (head in, response out) | [`EXCHANGE_TIMEOUT`] | closed |
//! | a stream's client not reading | [`STREAM_STALL`] | closed |
//! | request body | none accepted | 413, closed without reading it |
//! | methods | GET, HEAD | 405 with `Allow` |
//!
//! One request per connection (no keep-alive, so no pipelining): a client that never reads
//! its responses holds one connection until the exchange timeout, never the listener. The
//! whole listener is one thread whatever clients do (the unit's `TasksMax` cannot be reached
//! through it); an accept failure (out of descriptors) waits a moment and goes on. Shutdown
//! drops every connection at once: it never waits on a client.

use std::convert::Infallible;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http_body_util::{combinators::BoxBody, BodyExt, Full};
use hyper::body::{Body, Frame, Incoming};
use hyper::{Method, Request, Response, StatusCode};
use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore};

use super::{Status, MAX_STREAMS, PUSH_PERIOD};
use crate::error::{Error, Result};

/// Connections open at once; more are answered 503 and closed.
pub const MAX_CONNECTIONS: usize = 256;
/// Largest request head (request line and headers), bytes.
pub const MAX_HEAD_BYTES: usize = 8192;
/// Most headers in a request.
pub const MAX_HEADERS: usize = 32;
/// A client must send its whole request head within this.
pub const HEAD_TIMEOUT: Duration = Duration::from_secs(5);
/// A connection is closed this long after it was accepted unless it became a stream.
pub const EXCHANGE_TIMEOUT: Duration = Duration::from_secs(10);
/// A stream whose client took nothing for this long is closed.
pub const STREAM_STALL: Duration = Duration::from_secs(10);
/// After an accept failure (e.g. out of file descriptors), wait this long before the next.
const ACCEPT_BACKOFF: Duration = Duration::from_millis(100);

/// What the listener turned away or cut off, for `/metrics`.
#[derive(Debug, Default)]
pub struct ListenerCounters {
    /// Connections accepted and served.
    pub accepted: AtomicU64,
    /// Connections refused at the connection cap.
    pub refused: AtomicU64,
    /// Connections closed by a timeout (head, exchange or stalled stream).
    pub timed_out: AtomicU64,
    /// Requests answered with an error of the client's making (405, 413, 503 for streams).
    pub rejected: AtomicU64,
    /// Failed `accept` calls.
    pub accept_errors: AtomicU64,
}

type ResponseBody = BoxBody<Bytes, Infallible>;

/// The running listener.
pub struct HttpServer {
    stop: Arc<Notify>,
    thread: Option<std::thread::JoinHandle<()>>,
    address: std::net::SocketAddr,
}

impl HttpServer {
    /// Listens on `address` (HOST:PORT; port 0 picks one) and serves `status`.
    pub fn start(address: &str, status: Arc<Status>) -> Result<HttpServer> {
        let cannot = |e: std::io::Error| {
            Error::invalid("run.http", format!("cannot listen on {address}: {e}"))
        };
        let listener = std::net::TcpListener::bind(address).map_err(cannot)?;
        listener.set_nonblocking(true).map_err(cannot)?;
        let bound = listener.local_addr().map_err(cannot)?;
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()
            .map_err(|e| Error::Run(format!("cannot start the HTTP listener: {e}")))?;
        let stop = Arc::new(Notify::new());
        let thread = std::thread::Builder::new()
            .name("http".into())
            .spawn({
                let stop = stop.clone();
                move || {
                    runtime.block_on(accept(listener, status, stop));
                    // Open connections are dropped here, not waited on.
                    runtime.shutdown_background();
                }
            })
            .map_err(|e| Error::Run(format!("cannot start the HTTP thread: {e}")))?;
        Ok(HttpServer {
            stop,
            thread: Some(thread),
            address: bound,
        })
    }

    /// The address it listens on.
    pub fn address(&self) -> std::net::SocketAddr {
        self.address
    }
}

impl Drop for HttpServer {
    fn drop(&mut self) {
        // A permit is kept if the loop is not waiting yet, so the stop is never missed.
        self.stop.notify_one();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Accepts connections until told to stop.
async fn accept(listener: std::net::TcpListener, status: Arc<Status>, stop: Arc<Notify>) {
    let listener = match tokio::net::TcpListener::from_std(listener) {
        Ok(l) => l,
        Err(e) => {
            tracing::error!("HTTP listener: {e}");
            return;
        }
    };
    let connections = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    let streams = Arc::new(Semaphore::new(MAX_STREAMS));
    loop {
        let accepted = tokio::select! {
            () = stop.notified() => return,
            a = listener.accept() => a,
        };
        let socket = match accepted {
            Ok((socket, _)) => socket,
            Err(e) => {
                status
                    .listener
                    .accept_errors
                    .fetch_add(1, Ordering::Relaxed);
                tracing::warn!("HTTP listener: accept failed: {e}");
                tokio::time::sleep(ACCEPT_BACKOFF).await;
                continue;
            }
        };
        let Ok(permit) = connections.clone().try_acquire_owned() else {
            status.listener.refused.fetch_add(1, Ordering::Relaxed);
            // Best effort and never waiting: a full socket buffer just gets the close.
            let _ = socket.try_write(
                b"HTTP/1.1 503 Service Unavailable\r\nConnection: close\r\n\
                  Content-Type: text/plain\r\nContent-Length: 21\r\n\r\ntoo many connections\n",
            );
            continue;
        };
        status.listener.accepted.fetch_add(1, Ordering::Relaxed);
        tokio::spawn(connection(socket, permit, status.clone(), streams.clone()));
    }
}

/// When a connection is cut off: a monotonic instant, pushed on while a stream's client reads.
struct Deadline {
    start: Instant,
    at_ms: AtomicU64,
}

impl Deadline {
    fn new(after: Duration) -> Deadline {
        let d = Deadline {
            start: Instant::now(),
            at_ms: AtomicU64::new(0),
        };
        d.extend(after);
        d
    }

    fn extend(&self, by: Duration) {
        let at = self.start.elapsed() + by;
        self.at_ms.store(
            u64::try_from(at.as_millis()).unwrap_or(u64::MAX),
            Ordering::Relaxed,
        );
    }

    /// Resolves once the deadline passed without being pushed on.
    async fn passed(&self) {
        loop {
            let at = self.start + Duration::from_millis(self.at_ms.load(Ordering::Relaxed));
            if Instant::now() >= at {
                return;
            }
            tokio::time::sleep_until(at.into()).await;
        }
    }
}

/// Serves one connection: one request, its response, closed.
async fn connection(
    socket: tokio::net::TcpStream,
    _permit: OwnedSemaphorePermit,
    status: Arc<Status>,
    streams: Arc<Semaphore>,
) {
    let deadline = Arc::new(Deadline::new(EXCHANGE_TIMEOUT));
    let service = hyper::service::service_fn({
        let (deadline, status) = (deadline.clone(), status.clone());
        move |request: Request<Incoming>| {
            let response = respond(&request, &status, &streams, &deadline);
            async move { Ok::<_, Infallible>(response) }
        }
    });
    let served = hyper::server::conn::http1::Builder::new()
        .timer(hyper_util::rt::TokioTimer::new())
        .header_read_timeout(HEAD_TIMEOUT)
        .keep_alive(false)
        .max_buf_size(2 * MAX_HEAD_BYTES)
        .max_header_size(MAX_HEAD_BYTES)
        .max_headers(MAX_HEADERS)
        .serve_connection(hyper_util::rt::TokioIo::new(socket), service);
    tokio::select! {
        result = served => {
            if let Err(e) = result {
                if e.is_timeout() {
                    status.listener.timed_out.fetch_add(1, Ordering::Relaxed);
                }
                tracing::debug!("HTTP connection: {e}");
            }
        }
        () = deadline.passed() => {
            status.listener.timed_out.fetch_add(1, Ordering::Relaxed);
        }
    }
}

fn text(code: StatusCode, body: impl Into<Bytes>, kind: &'static str) -> Response<ResponseBody> {
    let mut r = Response::new(Full::new(body.into()).boxed());
    *r.status_mut() = code;
    r.headers_mut().insert(
        hyper::header::CONTENT_TYPE,
        hyper::header::HeaderValue::from_static(kind),
    );
    r
}

const PLAIN: &str = "text/plain; charset=utf-8";

/// The response to one request.
fn respond(
    request: &Request<Incoming>,
    status: &Arc<Status>,
    streams: &Arc<Semaphore>,
    deadline: &Arc<Deadline>,
) -> Response<ResponseBody> {
    let reject = |code: StatusCode, why: &'static str| {
        status.listener.rejected.fetch_add(1, Ordering::Relaxed);
        text(code, why, PLAIN)
    };
    if request.method() != Method::GET && request.method() != Method::HEAD {
        let mut r = reject(StatusCode::METHOD_NOT_ALLOWED, "only GET and HEAD\n");
        r.headers_mut().insert(
            hyper::header::ALLOW,
            hyper::header::HeaderValue::from_static("GET, HEAD"),
        );
        return r;
    }
    // A body is never read: any announced one is refused, whatever size it claims.
    if request.body().size_hint().upper() != Some(0) {
        return reject(
            StatusCode::PAYLOAD_TOO_LARGE,
            "request bodies are not accepted\n",
        );
    }
    let query = request.uri().query().unwrap_or("");
    match request.uri().path() {
        "/metrics" => text(
            StatusCode::OK,
            super::metrics(status),
            "text/plain; version=0.0.4; charset=utf-8",
        ),
        "/healthz" => text(StatusCode::OK, "ok\n", PLAIN),
        "/readyz" => match status.readiness() {
            Ok(()) => text(StatusCode::OK, "ready\n", PLAIN),
            Err(why) => text(
                StatusCode::SERVICE_UNAVAILABLE,
                format!("not ready: {why}\n"),
                PLAIN,
            ),
        },
        "/" | "/index.html" => text(
            StatusCode::OK,
            super::page(status, super::window_ms(query)),
            "text/html; charset=utf-8",
        ),
        "/events" => {
            let Ok(permit) = streams.clone().try_acquire_owned() else {
                return reject(
                    StatusCode::SERVICE_UNAVAILABLE,
                    "too many preview pages open\n",
                );
            };
            let window_us = (super::window_ms(query) * 1e3) as i64;
            deadline.extend(STREAM_STALL);
            let body = EventStream {
                status: status.clone(),
                window_us,
                tick: tokio::time::interval(PUSH_PERIOD),
                deadline: deadline.clone(),
                _permit: permit,
            };
            let mut r = Response::new(body.boxed());
            let h = r.headers_mut();
            h.insert(
                hyper::header::CONTENT_TYPE,
                hyper::header::HeaderValue::from_static("text/event-stream"),
            );
            h.insert(
                hyper::header::CACHE_CONTROL,
                hyper::header::HeaderValue::from_static("no-store"),
            );
            r
        }
        _ => text(StatusCode::NOT_FOUND, "not found\n", PLAIN),
    }
}

/// The page's server-sent events: one frame every [`PUSH_PERIOD`], for as long as the client
/// takes them (each poll means the client made room for more, so the stall deadline moves on).
struct EventStream {
    status: Arc<Status>,
    window_us: i64,
    tick: tokio::time::Interval,
    deadline: Arc<Deadline>,
    _permit: OwnedSemaphorePermit,
}

impl Body for EventStream {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<std::result::Result<Frame<Bytes>, Infallible>>> {
        self.deadline.extend(STREAM_STALL);
        match self.tick.poll_tick(cx) {
            Poll::Pending => Poll::Pending,
            Poll::Ready(_) => {
                let message = super::frame_event(&self.status, self.window_us);
                Poll::Ready(Some(Ok(Frame::data(Bytes::from(message)))))
            }
        }
    }
}
