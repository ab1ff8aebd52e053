//! The helper threads a stage borrows for work that splits: two jobs side by side (the motion
//! model's forward and backward flows and its sub-frames), or many pieces taken from one queue
//! by every helper until none is left (the pixel model's bands of tile rows, [`each`]).
//!
//! There is one helper per core by default; `V2CE_THREADS` sets how many threads work on a
//! stage's split work (1: none, everything on the stage's own thread, and no look-ahead
//! worker beside it).

/// Runs `a` here and, when `parallel`, `b` at the same time on one of the process's helper
/// threads (named `v2ce-helper`, one per core, started on first use and kept: a thread
/// spawned per call cost ~58 us on the 2-core machine of docs/results.md, more than the
/// smaller splits save); `b` runs here too, after `a`, where not parallel or no helper
/// thread can be had. Returns both results; a panic in either is resumed here.
pub fn side_by_side<A, B: Send>(
    parallel: bool,
    a: impl FnOnce() -> A,
    b: impl FnOnce() -> B + Send,
) -> (A, B) {
    let pool = match helpers() {
        Some(pool) if parallel => pool,
        _ => return (a(), b()),
    };
    let mut rb = None;
    let ra = pool.in_place_scope(|scope| {
        let slot = &mut rb;
        scope.spawn(move |_| *slot = Some(b()));
        a()
    });
    // The scope returns once the spawned job has run (or resumes its panic).
    let rb = rb.expect("the second job runs once");
    (ra, rb)
}

/// Runs `work` on every item: when `parallel`, here and on helper threads at once, each
/// taking the next item from one queue until none is left (so a few slow items do not hold
/// the others up, and a helper busy elsewhere leaves its share to the rest); else here in
/// order. Returns when every item is done; a panic in one is resumed here.
pub fn each<T: Send>(parallel: bool, items: &mut [T], work: impl Fn(&mut T) + Sync) {
    let pool = match helpers() {
        Some(pool) if parallel && items.len() > 1 => pool,
        _ => return items.iter_mut().for_each(work),
    };
    // Each item is taken by one thread only: its lock is never contended.
    let slots: Vec<std::sync::Mutex<&mut T>> =
        items.iter_mut().map(std::sync::Mutex::new).collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let take = || {
        while let Some(slot) = slots.get(next.fetch_add(1, std::sync::atomic::Ordering::Relaxed)) {
            work(&mut slot.lock().unwrap_or_else(|e| e.into_inner()));
        }
    };
    let helpers = (threads() - 1).min(slots.len() - 1);
    pool.in_place_scope(|scope| {
        for _ in 0..helpers {
            scope.spawn(|_| take());
        }
        take();
    });
}

/// How many threads work on a stage's split work: `V2CE_THREADS` where set to a number from 1
/// to [`MAX_THREADS`] (bounded in [`crate::limits`]), else the machine's cores.
pub fn threads() -> usize {
    static THREADS: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *THREADS.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        match std::env::var("V2CE_THREADS") {
            Ok(v) => match v.trim().parse::<usize>() {
                Ok(n) if (1..=MAX_THREADS).contains(&n) => n,
                _ => {
                    tracing::warn!(
                        "V2CE_THREADS={v:?} is not a number from 1 to {MAX_THREADS}: using the \
                         {cores} cores"
                    );
                    cores
                }
            },
            Err(_) => cores,
        }
        .clamp(1, MAX_THREADS)
    })
}

pub use crate::limits::MAX_THREADS;

/// The helper threads, started once: none with one thread (or where the system gives no
/// thread).
fn helpers() -> Option<&'static rayon::ThreadPool> {
    static POOL: std::sync::OnceLock<Option<rayon::ThreadPool>> = std::sync::OnceLock::new();
    POOL.get_or_init(|| {
        let threads = threads();
        if threads <= 1 {
            return None;
        }
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|_| "v2ce-helper".into())
            .build()
            .map_err(|e| tracing::warn!("no helper threads ({e}): split work runs on one thread"))
            .ok()
    })
    .as_ref()
}

/// Where to cut items of these amounts of `work` in two: the most leading items whose work is
/// at most half of the whole.
pub fn halfway(work: &[usize]) -> usize {
    let total: usize = work.iter().sum();
    let mut sum = 0;
    work.iter()
        .take_while(|&&n| {
            sum += n;
            2 * sum <= total
        })
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The cut leaves at most half of the work before it, and the next item would pass half.
    #[test]
    fn the_cut_leaves_at_most_half_before_it() {
        assert_eq!(halfway(&[]), 0);
        assert_eq!(halfway(&[1, 1, 1, 1]), 2);
        assert_eq!(halfway(&[5, 1, 1]), 0);
        assert_eq!(halfway(&[1, 1, 5]), 2);
        assert_eq!(halfway(&[0, 0, 3, 3]), 3);
        for work in [vec![3usize, 9, 2, 7, 1], vec![1; 17], vec![0, 8, 0]] {
            let at = halfway(&work);
            let total: usize = work.iter().sum();
            let before: usize = work[..at].iter().sum();
            assert!(2 * before <= total, "{work:?}: {at}");
            if at < work.len() {
                assert!(2 * (before + work[at]) > total, "{work:?}: {at}");
            }
        }
    }

    /// Every item is worked on once, in parallel or not.
    #[test]
    fn each_item_is_worked_on_once() {
        for parallel in [false, true] {
            let mut items: Vec<(usize, u32)> = (0..100).map(|i| (i, 0)).collect();
            each(parallel, &mut items, |(i, n)| *n += 1 + *i as u32);
            assert!(items.iter().all(|&(i, n)| n == 1 + i as u32));
        }
    }

    /// Both jobs run once, on a thread or here, and their results come back in order.
    #[test]
    fn both_jobs_run_and_return() {
        for parallel in [false, true] {
            let here = std::thread::current().id();
            let (a, (b, there)) = side_by_side(parallel, || 1, || (2, std::thread::current().id()));
            assert_eq!((a, b), (1, 2));
            assert_eq!(there == here, !parallel || threads() <= 1);
        }
    }
}
