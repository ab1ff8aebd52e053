//! Two jobs side by side: the one thread a stage borrows for work that splits in two (the
//! motion model's forward and backward flows and its sub-frames, the pixel model's bands).

/// Runs `a` here and, when `parallel`, `b` at the same time on a second thread named `name`
/// (`b` here too, after `a`, where not parallel or no thread can be had), and returns both
/// results.
pub fn side_by_side<A, B: Send>(
    name: &str,
    parallel: bool,
    a: impl FnOnce() -> A,
    b: impl FnOnce() -> B + Send,
) -> (A, B) {
    if !parallel {
        return (a(), b());
    }
    let b = std::sync::Mutex::new(Some(b));
    let run_b = || b.lock().ok().and_then(|mut f| f.take()).map(|f| f());
    std::thread::scope(|scope| {
        let handle = std::thread::Builder::new()
            .name(name.into())
            .spawn_scoped(scope, run_b);
        let ra = a();
        let rb = match handle {
            Ok(h) => h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)),
            Err(_) => None,
        };
        // Not run on the thread (none was had): run here.
        let rb = rb.or_else(run_b).expect("the second job runs once");
        (ra, rb)
    })
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
            let (a, (b, there)) = side_by_side(
                "v2ce-test",
                parallel,
                || 1,
                || (2, std::thread::current().id()),
            );
            assert_eq!((a, b), (1, 2));
            assert_eq!(there == here, !parallel);
        }
    }
}
