//! The listener itself: hyper's HTTP/1 server on a single-threaded tokio runtime of its own,
//! with every resource a client can make it hold bounded.
//!
//! | limit | value | past it |
//! |---|---|---|
//! | connections open at once | [`MAX_CONNECTIONS`] | the oldest half-open one evicted; with none, a short 503 written without waiting, then closed |
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
//! through it), and the preview's frames are encoded on one more ([`super::encoder`]); an
//! accept failure (out of descriptors) waits a moment and goes on. Shutdown drops every
//! connection at once: it never waits on a client.
//!
//! A connection is half-open until its whole request head has come. At the connection cap a
//! new connection takes the slot of the half-open one that has waited longest (evicted,
//! closed, counted), so a slowloris that holds every slot delays a probe by one accept, not by
//! the head timeout; a connection whose head came (an exchange being answered, a stream)
//! is never evicted, and when every slot holds one the newcomer gets the 503.

use std::collections::BTreeMap;
use std::convert::Infallible;
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use bytes::Bytes;
use http_body_util::{combinators::BoxBody, BodyExt, Full};
use hyper::body::{Body, Frame, Incoming};
use hyper::{Method, Request, Response, StatusCode};
use tokio::sync::{Notify, OwnedSemaphorePermit, Semaphore};

use super::encoder::{Encoder, Subscription, Wants};
use super::{Status, MAX_STREAMS};
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
/// How long a new connection waits for the slot of the half-open one it evicted (which lets
/// go of it as soon as this thread runs its task: at once, in practice).
const EVICTION_WAIT: Duration = Duration::from_millis(100);
/// How long a page load waits for its first frame from the encoder (a round is due within a
/// push period); past it the page is served without one and the stream brings it.
const PAGE_FRAME_WAIT: Duration = Duration::from_secs(2);

/// What the listener turned away or cut off, for `/metrics`.
#[derive(Debug, Default)]
pub struct ListenerCounters {
    /// Connections accepted and served.
    pub accepted: AtomicU64,
    /// Connections refused at the connection cap (every slot held by a connection whose head
    /// came).
    pub refused: AtomicU64,
    /// Half-open connections (no whole request head yet) closed at the cap to make room for a
    /// new one, the oldest first.
    pub evicted: AtomicU64,
    /// Connections closed by a timeout (head, exchange or stalled stream).
    pub timed_out: AtomicU64,
    /// Requests answered with an error of the client's making (405, 413, 503 for streams).
    pub rejected: AtomicU64,
    /// Failed `accept` calls.
    pub accept_errors: AtomicU64,
    /// Preview frames drawn and encoded: one per push period and accumulation window, however
    /// many pages show it.
    pub preview_frames: AtomicU64,
}

type ResponseBody = BoxBody<Bytes, Infallible>;

/// The running listener.
pub struct HttpServer {
    stop: Arc<Notify>,
    thread: Option<std::thread::JoinHandle<()>>,
    address: std::net::SocketAddr,
    encoder: Arc<Encoder>,
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
        let encoder = Arc::new(Encoder::new(status.clone()));
        let thread = std::thread::Builder::new()
            .name("http".into())
            .spawn({
                let (stop, encoder) = (stop.clone(), encoder.clone());
                move || {
                    runtime.block_on(accept(listener, status, encoder, stop));
                    // Open connections are dropped here, not waited on.
                    runtime.shutdown_background();
                }
            })
            .map_err(|e| Error::Run(format!("cannot start the HTTP thread: {e}")))?;
        Ok(HttpServer {
            stop,
            thread: Some(thread),
            address: bound,
            encoder,
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
        // After the listener: no stream subscribes any more; at most the frame being encoded
        // is waited for.
        self.encoder.stop();
    }
}

/// The connections that have not sent their whole request head yet, oldest first, each with
/// the signal that evicts it.
#[derive(Default)]
struct HalfOpen {
    next: u64,
    waiting: BTreeMap<u64, Arc<Notify>>,
}

/// The half-open connections, shared by the accept loop and the connections (all on the
/// listener's one thread: the lock is never contended).
type HalfOpenList = Arc<Mutex<HalfOpen>>;

fn lock(half_open: &HalfOpenList) -> std::sync::MutexGuard<'_, HalfOpen> {
    half_open.lock().unwrap_or_else(|e| e.into_inner())
}

/// Signals the oldest half-open connection to close, if there is one.
fn evict_oldest(half_open: &HalfOpenList) -> bool {
    match lock(half_open).waiting.pop_first() {
        Some((_, evict)) => {
            evict.notify_one();
            true
        }
        None => false,
    }
}

/// A connection's place among the half-open ones, left when its head has come (or it closed).
struct HeadWait {
    id: u64,
    half_open: HalfOpenList,
}

impl HeadWait {
    /// A new connection, the youngest half-open one; and the signal that evicts it.
    fn enter(half_open: &HalfOpenList) -> (HeadWait, Arc<Notify>) {
        let evict = Arc::new(Notify::new());
        let mut list = lock(half_open);
        let id = list.next;
        list.next += 1;
        list.waiting.insert(id, evict.clone());
        drop(list);
        let wait = HeadWait {
            id,
            half_open: half_open.clone(),
        };
        (wait, evict)
    }

    /// The head has come: no longer evictable.
    fn leave(&self) {
        lock(&self.half_open).waiting.remove(&self.id);
    }
}

impl Drop for HeadWait {
    fn drop(&mut self) {
        self.leave();
    }
}

/// Accepts connections until told to stop.
async fn accept(
    listener: std::net::TcpListener,
    status: Arc<Status>,
    encoder: Arc<Encoder>,
    stop: Arc<Notify>,
) {
    let listener = match tokio::net::TcpListener::from_std(listener) {
        Ok(l) => l,
        Err(e) => {
            tracing::error!("HTTP listener: {e}");
            return;
        }
    };
    let connections = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    let streams = Arc::new(Semaphore::new(MAX_STREAMS));
    let half_open = HalfOpenList::default();
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
        let permit = match connections.clone().try_acquire_owned() {
            Ok(permit) => Some(permit),
            // The evicted connection's task runs next on this thread and lets go of its slot.
            Err(_) if evict_oldest(&half_open) => {
                tokio::time::timeout(EVICTION_WAIT, connections.clone().acquire_owned())
                    .await
                    .ok()
                    .and_then(|p| p.ok())
            }
            Err(_) => None,
        };
        let Some(permit) = permit else {
            status.listener.refused.fetch_add(1, Ordering::Relaxed);
            // Best effort and never waiting: a full socket buffer just gets the close.
            let _ = socket.try_write(
                b"HTTP/1.1 503 Service Unavailable\r\nConnection: close\r\n\
                  Content-Type: text/plain\r\nContent-Length: 21\r\n\r\ntoo many connections\n",
            );
            continue;
        };
        status.listener.accepted.fetch_add(1, Ordering::Relaxed);
        let (head, evict) = HeadWait::enter(&half_open);
        let shared = Shared {
            status: status.clone(),
            streams: streams.clone(),
            encoder: encoder.clone(),
        };
        tokio::spawn(connection(socket, permit, shared, head, evict));
    }
}

/// What every connection shares.
#[derive(Clone)]
struct Shared {
    status: Arc<Status>,
    streams: Arc<Semaphore>,
    encoder: Arc<Encoder>,
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

/// Serves one connection: one request, its response, closed; or evicted while its head has
/// not come.
async fn connection(
    socket: tokio::net::TcpStream,
    _permit: OwnedSemaphorePermit,
    shared: Shared,
    head: HeadWait,
    evict: Arc<Notify>,
) {
    let status = shared.status.clone();
    let deadline = Arc::new(Deadline::new(EXCHANGE_TIMEOUT));
    let service = hyper::service::service_fn({
        let deadline = deadline.clone();
        move |request: Request<Incoming>| {
            // Called once the whole head has been read.
            head.leave();
            let reply = respond(&request, &shared, &deadline);
            let shared = shared.clone();
            async move {
                let response = match reply {
                    Reply::Now(response) => response,
                    Reply::Page(window_ms) => page(&shared, window_ms).await,
                };
                Ok::<_, Infallible>(response)
            }
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
        // Checked first: an evicted connection is gone even when its head has just come.
        biased;
        () = evict.notified() => {
            status.listener.evicted.fetch_add(1, Ordering::Relaxed);
        }
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

/// A response: at once, or the page (which waits for its first frame).
enum Reply {
    Now(Response<ResponseBody>),
    /// The page, with this accumulation window (ms).
    Page(f64),
}

/// The page with its first frame, from the encoder (or without, when none comes in time).
async fn page(shared: &Shared, window_ms: f64) -> Response<ResponseBody> {
    let window_us = (window_ms * 1e3) as i64;
    let png = match shared.encoder.subscribe(window_us, Wants::Page) {
        Ok(Some(frames)) => tokio::time::timeout(PAGE_FRAME_WAIT, frames.next())
            .await
            .ok()
            .map(|frame| frame.png_base64.clone()),
        Ok(None) => None,
        Err(e) => {
            tracing::warn!("HTTP listener: {e}");
            None
        }
    };
    text(
        StatusCode::OK,
        super::page(&shared.status, window_ms, png.as_deref()),
        "text/html; charset=utf-8",
    )
}

/// The response to one request.
fn respond(request: &Request<Incoming>, shared: &Shared, deadline: &Arc<Deadline>) -> Reply {
    let status = &shared.status;
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
        return Reply::Now(r);
    }
    // A body is never read: any announced one is refused, whatever size it claims.
    if request.body().size_hint().upper() != Some(0) {
        return Reply::Now(reject(
            StatusCode::PAYLOAD_TOO_LARGE,
            "request bodies are not accepted\n",
        ));
    }
    let query = request.uri().query().unwrap_or("");
    Reply::Now(match request.uri().path() {
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
        "/" | "/index.html" => return Reply::Page(super::window_ms(query)),
        "/events" => {
            let Ok(permit) = shared.streams.clone().try_acquire_owned() else {
                return Reply::Now(reject(
                    StatusCode::SERVICE_UNAVAILABLE,
                    "too many preview pages open\n",
                ));
            };
            let window_us = (super::window_ms(query) * 1e3) as i64;
            let frames = match shared.encoder.subscribe(window_us, Wants::Stream) {
                Ok(Some(frames)) => frames,
                // (A stream's window is never refused; the thread may fail to start.)
                failed => {
                    if let Err(e) = failed {
                        tracing::warn!("HTTP listener: {e}");
                    }
                    return Reply::Now(text(
                        StatusCode::SERVICE_UNAVAILABLE,
                        "the preview encoder is not running\n",
                        PLAIN,
                    ));
                }
            };
            deadline.extend(STREAM_STALL);
            let body = EventStream {
                frames,
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
    })
}

/// The page's server-sent events: the encoder's frame every [`super::PUSH_PERIOD`] (the latest one,
/// where the client took its last late), for as long as the client takes them (each poll
/// means the client made room for more, so the stall deadline moves on). The bytes are the
/// encoder's, shared by every stream of the same window.
struct EventStream {
    frames: Subscription,
    deadline: Arc<Deadline>,
    _permit: OwnedSemaphorePermit,
}

impl Body for EventStream {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<std::result::Result<Frame<Bytes>, Infallible>>> {
        self.deadline.extend(STREAM_STALL);
        match self.frames.poll_next(cx) {
            Poll::Pending => Poll::Pending,
            Poll::Ready(frame) => Poll::Ready(Some(Ok(Frame::data(frame.event.clone())))),
        }
    }
}
