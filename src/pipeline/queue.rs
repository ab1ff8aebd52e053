//! Bounded queues between pipeline stages, with a policy for when one is full.
//!
//! - [`QueuePolicy::Block`]: the producer waits for room; nothing is ever lost (offline
//!   conversion).
//! - [`QueuePolicy::DropOldest`]: the producer never waits; the oldest queued item is evicted
//!   and counted (live capture: the output stays current when a stage falls behind).
//!
//! Every link is a `crossbeam-channel` bounded array channel, lock-free on the fast path. A
//! `ringbuf` SPSC ring was the first choice for the single-producer links, but its split halves
//! cannot evict from the producer side (drop-oldest needs the producer to pop the oldest item,
//! which the array channel allows through a second receiver handle), and it has neither a
//! blocking wait nor a disconnect signal, which the shutdown protocol relies on: a stage ends
//! when its input is drained and every producer has gone, so a flush needs no extra messages.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use crossbeam_channel::{Receiver, Sender, TrySendError};
use serde::{Deserialize, Serialize};

/// What a full queue does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum QueuePolicy {
    /// Wait for room: never lose data.
    #[default]
    Block,
    /// Evict the oldest item and count it: never wait.
    DropOldest,
}

impl QueuePolicy {
    /// Parses `block` or `drop-oldest`.
    pub fn from_name(name: &str) -> crate::Result<Self> {
        match name {
            "block" => Ok(QueuePolicy::Block),
            "drop-oldest" => Ok(QueuePolicy::DropOldest),
            _ => Err(crate::Error::invalid(
                "queue policy",
                format!("{name:?} (expected block or drop-oldest)"),
            )),
        }
    }

    /// The name used in the config.
    pub fn name(self) -> &'static str {
        match self {
            QueuePolicy::Block => "block",
            QueuePolicy::DropOldest => "drop-oldest",
        }
    }
}

/// How much an item counts for in the drop statistics besides itself (the events of a batch).
pub trait Weight {
    /// Events (or other units) the item carries.
    fn weight(&self) -> u64;
}

/// The counters of one queue, shared with the stats reporter.
pub struct QueueStats {
    /// The queue's name in logs (`frames`, `stage1`, ...).
    pub name: String,
    /// Capacity in items.
    pub capacity: usize,
    pushed: AtomicU64,
    dropped: AtomicU64,
    dropped_weight: AtomicU64,
    popped: AtomicU64,
}

impl QueueStats {
    /// Items accepted.
    pub fn pushed(&self) -> u64 {
        self.pushed.load(Ordering::Relaxed)
    }
    /// Items evicted (drop-oldest only).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
    /// The evicted items' weight (events in dropped batches).
    pub fn dropped_weight(&self) -> u64 {
        self.dropped_weight.load(Ordering::Relaxed)
    }
    /// Items waiting now.
    pub fn depth(&self) -> usize {
        let out = self.popped.load(Ordering::Relaxed) + self.dropped();
        self.pushed().saturating_sub(out) as usize
    }
}

impl std::fmt::Debug for QueueStats {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("QueueStats")
            .field("name", &self.name)
            .field("pushed", &self.pushed())
            .field("dropped", &self.dropped())
            .field("depth", &self.depth())
            .finish()
    }
}

/// The producing end.
pub struct QueueTx<T> {
    tx: Sender<T>,
    // Drop-oldest evicts through its own receiver handle.
    evict: Option<Receiver<T>>,
    stats: Arc<QueueStats>,
}

/// The consuming end: [`QueueRx::recv`] returns `None` once every producer has gone and the
/// queue is drained.
pub struct QueueRx<T> {
    rx: Receiver<T>,
    stats: Arc<QueueStats>,
}

/// The receiving side went away; the item comes back.
#[derive(Debug)]
pub struct Closed<T>(pub T);

/// A bounded queue of `capacity` (at least 1) items.
pub fn queue<T: Weight + Send + 'static>(
    name: &str,
    capacity: usize,
    policy: QueuePolicy,
) -> (QueueTx<T>, QueueRx<T>, Arc<QueueStats>) {
    let (tx, rx) = crossbeam_channel::bounded(capacity.max(1));
    let stats = Arc::new(QueueStats {
        name: name.to_string(),
        capacity: capacity.max(1),
        pushed: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
        dropped_weight: AtomicU64::new(0),
        popped: AtomicU64::new(0),
    });
    let evict = (policy == QueuePolicy::DropOldest).then(|| rx.clone());
    (
        QueueTx {
            tx,
            evict,
            stats: stats.clone(),
        },
        QueueRx {
            rx,
            stats: stats.clone(),
        },
        stats,
    )
}

impl<T: Weight> QueueTx<T> {
    /// Queues `item` by the policy. Fails only when the consumer has gone.
    pub fn push(&self, mut item: T) -> Result<(), Closed<T>> {
        match &self.evict {
            None => self.tx.send(item).map_err(|e| Closed(e.0))?,
            Some(evict) => loop {
                match self.tx.try_send(item) {
                    Ok(()) => break,
                    Err(TrySendError::Disconnected(back)) => return Err(Closed(back)),
                    Err(TrySendError::Full(back)) => {
                        item = back;
                        if let Ok(old) = evict.try_recv() {
                            // Counted as dropped, not popped.
                            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
                            self.stats
                                .dropped_weight
                                .fetch_add(old.weight(), Ordering::Relaxed);
                        }
                    }
                }
            },
        }
        self.stats.pushed.fetch_add(1, Ordering::Relaxed);
        Ok(())
    }
}

impl<T> QueueRx<T> {
    /// Whether nothing waits in the queue now.
    pub fn is_empty(&self) -> bool {
        self.rx.is_empty()
    }

    /// The next item; `None` when every producer has gone and nothing is left.
    pub fn recv(&self) -> Option<T> {
        let item = self.rx.recv().ok()?;
        self.stats.popped.fetch_add(1, Ordering::Relaxed);
        Some(item)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    impl Weight for u32 {
        fn weight(&self) -> u64 {
            u64::from(*self)
        }
    }

    #[test]
    fn drop_oldest_evicts_and_counts() {
        let (tx, rx, stats) = queue::<u32>("t", 2, QueuePolicy::DropOldest);
        for i in 1..=5 {
            tx.push(i).unwrap();
        }
        assert_eq!(stats.depth(), 2);
        assert_eq!(stats.dropped(), 3);
        assert_eq!(stats.dropped_weight(), 1 + 2 + 3);
        assert_eq!(stats.pushed(), 5);
        drop(tx);
        assert_eq!(rx.recv(), Some(4));
        assert_eq!(rx.recv(), Some(5));
        assert_eq!(rx.recv(), None);
    }

    #[test]
    fn block_loses_nothing_and_drains_after_close() {
        let (tx, rx, stats) = queue::<u32>("t", 1, QueuePolicy::Block);
        let producer = std::thread::spawn(move || {
            for i in 0..1000 {
                tx.push(i).unwrap();
            }
        });
        let mut got = Vec::new();
        while let Some(v) = rx.recv() {
            got.push(v);
        }
        producer.join().unwrap();
        assert_eq!(got, (0..1000).collect::<Vec<_>>());
        assert_eq!(stats.dropped(), 0);
    }

    #[test]
    fn push_fails_when_the_consumer_is_gone() {
        for policy in [QueuePolicy::Block, QueuePolicy::DropOldest] {
            let (tx, rx, _) = queue::<u32>("t", 1, policy);
            drop(rx);
            if policy == QueuePolicy::Block {
                assert!(tx.push(1).is_err());
            } else {
                // The evicting handle keeps the channel open: a gone consumer is seen by the
                // stage's own liveness flag instead, and pushing never blocks.
                tx.push(1).unwrap();
                tx.push(2).unwrap();
            }
        }
    }
}
