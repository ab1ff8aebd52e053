//! The preview's encoder: one thread of its own (`v2ce-preview`, started by the first page load
//! or stream, never more than one) that draws and encodes the preview frames off the
//! listener's thread, once per [`PUSH_PERIOD`] and accumulation window however many streams
//! share it.
//!
//! A round draws the frame of each window wanted (a PNG and the stats, as one server-sent
//! event) and leaves it in each subscriber's mailbox over what was there: the latest frame
//! wins, so a stream whose client reads slowly skips frames and never queues them. One round
//! runs at a time and rounds start at most once a period; when a round takes longer than a
//! period, the next one starts as it ends, with the newest events. A subscriber gets the last
//! round's frame at once when that round is less than a period old.
//!
//! What a client can make it do is bounded: the windows of the open streams (at most
//! [`super::MAX_STREAMS`]) and of at most [`MAX_PAGE_WINDOWS`] others wanted by page loads at once (a
//! page load with yet another window is served without its first frame), so a round encodes
//! at most `MAX_STREAMS + MAX_PAGE_WINDOWS` frames and the encoder never takes more than one
//! core. Subscribers are at most one per open connection.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, Weak};
use std::task::{Context, Poll, Waker};
use std::time::Instant;

use bytes::Bytes;

use super::{Status, PUSH_PERIOD};
use crate::error::{Error, Result};

/// Accumulation windows that page loads may add to the streams' at once.
pub const MAX_PAGE_WINDOWS: usize = 4;

/// The encoder thread's name (as `/proc` and `top -H` show it).
pub const THREAD_NAME: &str = "v2ce-preview";

/// One round's frame for one window.
pub struct Encoded {
    /// The server-sent event a stream sends: `data: {...}\n\n`.
    pub event: Bytes,
    /// The PNG in base64, which a page load inlines.
    pub png_base64: String,
}

/// Who wants a window's frames.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum Wants {
    /// An `/events` stream (bounded by [`super::MAX_STREAMS`]): every round's frame.
    Stream,
    /// A page load: the first frame, then it lets go.
    Page,
}

/// A subscriber's latest frame, and the task waiting for the next.
#[derive(Default)]
struct Mailbox {
    slot: Mutex<Slot>,
}

#[derive(Default)]
struct Slot {
    latest: Option<Arc<Encoded>>,
    waker: Option<Waker>,
}

impl Mailbox {
    /// Leaves `frame` over whatever was there and wakes the waiting task.
    fn put(&self, frame: Arc<Encoded>) {
        let waker = {
            let mut slot = lock(&self.slot);
            slot.latest = Some(frame);
            slot.waker.take()
        };
        if let Some(w) = waker {
            w.wake();
        }
    }
}

/// The frames of one window, for as long as this is held.
pub struct Subscription {
    mailbox: Arc<Mailbox>,
}

impl Subscription {
    /// The latest frame not yet taken, or `Pending` (woken by the next round).
    pub fn poll_next(&self, cx: &mut Context<'_>) -> Poll<Arc<Encoded>> {
        let mut slot = lock(&self.mailbox.slot);
        match slot.latest.take() {
            Some(frame) => Poll::Ready(frame),
            None => {
                if !slot.waker.as_ref().is_some_and(|w| w.will_wake(cx.waker())) {
                    slot.waker = Some(cx.waker().clone());
                }
                Poll::Pending
            }
        }
    }

    /// The next frame.
    pub async fn next(&self) -> Arc<Encoded> {
        std::future::poll_fn(|cx| self.poll_next(cx)).await
    }
}

struct Subscriber {
    window_us: i64,
    wants: Wants,
    mailbox: Weak<Mailbox>,
}

/// A round's frames, by window (us).
type Frames = Vec<(i64, Arc<Encoded>)>;

#[derive(Default)]
struct State {
    /// At most one per open connection; the dropped ones are swept out as they are seen.
    subscribers: Vec<Subscriber>,
    /// The last round: when it started and its frames.
    last: Option<(Instant, Frames)>,
    thread: Option<std::thread::JoinHandle<()>>,
}

struct Shared {
    status: Arc<Status>,
    state: Mutex<State>,
    /// Signalled on a new subscriber and on stop.
    wake: Condvar,
    stop: AtomicBool,
}

/// The listener's handle on the encoder thread.
pub struct Encoder {
    shared: Arc<Shared>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Encoder {
    /// An encoder of `status`'s preview; its thread starts with the first subscriber.
    pub fn new(status: Arc<Status>) -> Encoder {
        Encoder {
            shared: Arc::new(Shared {
                status,
                state: Mutex::new(State::default()),
                wake: Condvar::new(),
                stop: AtomicBool::new(false),
            }),
        }
    }

    /// The frames of the last `window_us` of events, from the next round on (from the last
    /// one, when it is recent); `None` for a page load with a window past
    /// [`MAX_PAGE_WINDOWS`]. Fails when the thread cannot be started.
    pub fn subscribe(&self, window_us: i64, wants: Wants) -> Result<Option<Subscription>> {
        let mut state = lock(&self.shared.state);
        state.subscribers.retain(|s| s.mailbox.strong_count() > 0);
        let wanted = state.subscribers.iter().any(|s| s.window_us == window_us);
        if wants == Wants::Page && !wanted {
            // The windows that page loads alone want.
            let mut pages: Vec<i64> = state
                .subscribers
                .iter()
                .filter(|s| s.wants == Wants::Page && !wanted_by_stream(&state, s.window_us))
                .map(|s| s.window_us)
                .collect();
            pages.sort_unstable();
            pages.dedup();
            if pages.len() >= MAX_PAGE_WINDOWS {
                return Ok(None);
            }
        }
        if self.shared.stop.load(Ordering::Relaxed) {
            return Err(Error::Run("the preview encoder has stopped".into()));
        }
        // Started with the first subscriber; started again should it have ended (a panic).
        if state.thread.as_ref().is_none_or(|t| t.is_finished()) {
            if let Some(ended) = state.thread.take() {
                let _ = ended.join();
            }
            let shared = self.shared.clone();
            let thread = std::thread::Builder::new()
                .name(THREAD_NAME.into())
                .spawn(move || run(&shared))
                .map_err(|e| Error::Run(format!("cannot start the preview encoder: {e}")))?;
            state.thread = Some(thread);
        }
        let mailbox = Arc::new(Mailbox::default());
        if let Some((at, frames)) = &state.last {
            if at.elapsed() < PUSH_PERIOD {
                if let Some((_, frame)) = frames.iter().find(|(w, _)| *w == window_us) {
                    mailbox.put(frame.clone());
                }
            }
        }
        state.subscribers.push(Subscriber {
            window_us,
            wants,
            mailbox: Arc::downgrade(&mailbox),
        });
        self.shared.wake.notify_one();
        Ok(Some(Subscription { mailbox }))
    }

    /// Stops the thread: at once when it waits, after the frame it encodes otherwise.
    pub fn stop(&self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        let thread = {
            let mut state = lock(&self.shared.state);
            self.shared.wake.notify_one();
            state.thread.take()
        };
        if let Some(t) = thread {
            let _ = t.join();
        }
    }
}

impl Drop for Encoder {
    fn drop(&mut self) {
        self.stop();
    }
}

fn wanted_by_stream(state: &State, window_us: i64) -> bool {
    state
        .subscribers
        .iter()
        .any(|s| s.wants == Wants::Stream && s.window_us == window_us)
}

/// The thread: a round whenever there are subscribers and the last round is a period old.
fn run(shared: &Shared) {
    let stopped = || shared.stop.load(Ordering::Relaxed);
    let mut last_start: Option<Instant> = None;
    loop {
        let windows: Vec<i64> = {
            let mut state = lock(&shared.state);
            loop {
                if stopped() {
                    return;
                }
                state.subscribers.retain(|s| s.mailbox.strong_count() > 0);
                let due = last_start.map(|t| t + PUSH_PERIOD);
                let now = Instant::now();
                state = if state.subscribers.is_empty() {
                    // Nobody looks: the frames kept would be stale by the next subscriber.
                    state.last = None;
                    shared.wake.wait(state).unwrap_or_else(|e| e.into_inner())
                } else if let Some(due) = due.filter(|due| now < *due) {
                    shared
                        .wake
                        .wait_timeout(state, due - now)
                        .unwrap_or_else(|e| e.into_inner())
                        .0
                } else {
                    break;
                };
            }
            let mut windows: Vec<i64> = state.subscribers.iter().map(|s| s.window_us).collect();
            windows.sort_unstable();
            windows.dedup();
            windows
        };
        let started = Instant::now();
        last_start = Some(started);
        let mut frames: Frames = Vec::with_capacity(windows.len());
        for window_us in windows {
            if stopped() {
                return;
            }
            frames.push((
                window_us,
                Arc::new(super::encode(&shared.status, window_us)),
            ));
        }
        let mut state = lock(&shared.state);
        for s in &state.subscribers {
            let Some(mailbox) = s.mailbox.upgrade() else {
                continue;
            };
            // A subscriber whose window came during the round gets the next round's.
            if let Some((_, frame)) = frames.iter().find(|(w, _)| *w == s.window_us) {
                mailbox.put(frame.clone());
            }
        }
        state.last = Some((started, frames));
    }
}

#[cfg(test)]
mod tests {
    use super::super::MAX_STREAMS;
    use super::*;
    use crate::sink::preview::PreviewBuffer;
    use std::time::Duration;

    fn status() -> Arc<Status> {
        Arc::new(Status {
            counters: Arc::new(crate::pipeline::stats::Counters::new()),
            preview: PreviewBuffer::new(8, 6),
            tier: "physics".into(),
            preset: "davis346".into(),
            settings: Vec::new(),
            stall: Duration::from_secs(60),
            running: AtomicBool::new(true),
            listener: super::super::ListenerCounters::default(),
        })
    }

    fn wait(s: &Subscription) -> Arc<Encoded> {
        let started = Instant::now();
        loop {
            let waker = Waker::noop();
            if let Poll::Ready(f) = s.poll_next(&mut Context::from_waker(waker)) {
                return f;
            }
            assert!(started.elapsed() < Duration::from_secs(10), "no frame");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    fn threads_named(name: &str) -> usize {
        std::fs::read_dir("/proc/self/task")
            .into_iter()
            .flatten()
            .flatten()
            .filter(|t| {
                std::fs::read_to_string(t.path().join("comm")).is_ok_and(|c| c.trim() == name)
            })
            .count()
    }

    #[test]
    fn one_thread_encodes_each_window_once_a_round_for_every_subscriber() {
        let status = status();
        let encoder = Encoder::new(status.clone());
        let started = Instant::now();
        let streams: Vec<Subscription> = (0..MAX_STREAMS)
            .map(|_| encoder.subscribe(33_000, Wants::Stream).unwrap().unwrap())
            .collect();
        for _ in 0..3 {
            let frames: Vec<Arc<Encoded>> = streams.iter().map(wait).collect();
            assert!(frames[0].event.starts_with(b"data: {"));
            assert!(frames[0].event.ends_with(b"\n\n"));
            assert!(!frames[0].png_base64.is_empty());
        }
        // Every stream got 3 frames; the rounds, not the streams, set what was encoded.
        let rounds = started.elapsed().as_secs_f64() / PUSH_PERIOD.as_secs_f64();
        let encoded = status.listener.preview_frames.load(Ordering::Relaxed);
        assert!(
            encoded as f64 <= rounds + 2.0,
            "{encoded} frames encoded in {rounds:.1} periods for {MAX_STREAMS} streams"
        );
        assert_eq!(threads_named(THREAD_NAME), 1);
        // Page loads: a few windows more, then none.
        let pages: Vec<Option<Subscription>> = (0..MAX_PAGE_WINDOWS + 1)
            .map(|i| {
                encoder
                    .subscribe(1_000 * (i as i64 + 1), Wants::Page)
                    .unwrap()
            })
            .collect();
        assert!(pages[..MAX_PAGE_WINDOWS].iter().all(Option::is_some));
        assert!(pages[MAX_PAGE_WINDOWS].is_none());
        // A page that shares a window with a stream costs nothing and is never refused.
        assert!(encoder.subscribe(33_000, Wants::Page).unwrap().is_some());
        drop(pages);
        assert!(encoder.subscribe(99_000, Wants::Page).unwrap().is_some());
        encoder.stop();
        // Joined; the kernel lists a thread that has ended until it has released it, a moment
        // after the join returns (the test failed 1 run in 5 on a busy machine): wait for that.
        let stopped = Instant::now();
        while threads_named(THREAD_NAME) > 0 && stopped.elapsed() < Duration::from_secs(5) {
            std::thread::sleep(Duration::from_millis(10));
        }
        assert_eq!(threads_named(THREAD_NAME), 0);
    }
}
