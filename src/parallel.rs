//! Two jobs side by side: the helper thread a stage borrows for work that splits in two (the
//! motion model's forward and backward flows and its sub-frames, the pixel model's bands).

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

/// The helper threads, started once (none where the system gives no thread).
fn helpers() -> Option<&'static rayon::ThreadPool> {
    static POOL: std::sync::OnceLock<Option<rayon::ThreadPool>> = std::sync::OnceLock::new();
    POOL.get_or_init(|| {
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        rayon::ThreadPoolBuilder::new()
            .num_threads(cores.max(1))
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

    /// Both jobs run once, on a thread or here, and their results come back in order.
    #[test]
    fn both_jobs_run_and_return() {
        for parallel in [false, true] {
            let here = std::thread::current().id();
            let (a, (b, there)) = side_by_side(parallel, || 1, || (2, std::thread::current().id()));
            assert_eq!((a, b), (1, 2));
            assert_eq!(there == here, !parallel);
        }
    }
}
