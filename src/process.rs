//! The process's own use of the machine: CPU time, resident and peak memory, and the address
//! space it takes, as the kernel reports them (`getrusage`, `/proc/self/statm`, the page size
//! from `sysconf`). The daemon's stats, `v2ce model bench` and the memory limits read them here.

/// The process's CPU time and memory.
#[derive(Debug, Clone, Copy, Default)]
pub struct ProcessUsage {
    /// User + system CPU seconds.
    pub cpu_s: f64,
    /// Resident set now, KiB (0 where /proc is missing).
    pub rss_kib: u64,
    /// Peak resident set, KiB.
    pub max_rss_kib: u64,
}

impl ProcessUsage {
    /// Reads them now.
    pub fn now() -> Self {
        // SAFETY: getrusage writes one plain struct that we own.
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        let ok = unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) } == 0;
        let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
        let (cpu_s, max_rss_kib) = if ok {
            (
                secs(ru.ru_utime) + secs(ru.ru_stime),
                ru.ru_maxrss.max(0) as u64,
            )
        } else {
            (0.0, 0)
        };
        ProcessUsage {
            cpu_s,
            rss_kib: resident_bytes().map_or(0, |b| b / 1024),
            max_rss_kib,
        }
    }
}

/// Each of the process's threads now: its id, its name (the kernel's `comm`, at most 15 bytes)
/// and its user + system CPU seconds (`/proc/self/task/*/stat`; empty where /proc is missing).
pub fn thread_cpu() -> Vec<(u32, String, f64)> {
    // SAFETY: sysconf only reads a system constant.
    let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    let ticks = if ticks > 0 { ticks as f64 } else { 100.0 };
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return Vec::new();
    };
    dir.filter_map(|entry| {
        let entry = entry.ok()?;
        let tid: u32 = entry.file_name().to_str()?.parse().ok()?;
        let stat = std::fs::read_to_string(entry.path().join("stat")).ok()?;
        let (head, rest) = stat.rsplit_once(')')?;
        let name = head.split_once('(')?.1.to_string();
        // After the name: state (field 3), ..., utime (14) and stime (15).
        let fields: Vec<&str> = rest.split_whitespace().collect();
        let utime: f64 = fields.get(11)?.parse().ok()?;
        let stime: f64 = fields.get(12)?.parse().ok()?;
        Some((tid, name, (utime + stime) / ticks))
    })
    .collect()
}

/// Thread id -> (name, CPU seconds at the start or when first seen, latest CPU seconds).
type Readings = std::collections::HashMap<u32, (String, f64, f64)>;

/// Follows the CPU time of every thread of the process while it runs (threads that end are
/// kept with their last reading, taken every 200 ms).
pub struct ThreadCpu {
    done: std::sync::Arc<std::sync::atomic::AtomicBool>,
    handle: Option<std::thread::JoinHandle<Readings>>,
    started: std::time::Instant,
}

impl ThreadCpu {
    /// Starts following (its own thread, `cpu-sampler`, is left out of the figures).
    pub fn start() -> std::io::Result<ThreadCpu> {
        use std::sync::atomic::Ordering;
        let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let baseline: std::collections::HashMap<u32, f64> =
            thread_cpu().into_iter().map(|(t, _, c)| (t, c)).collect();
        let handle = std::thread::Builder::new()
            .name("cpu-sampler".into())
            .spawn({
                let done = done.clone();
                move || {
                    // tid -> (name, CPU at the start or first sight, latest CPU)
                    let mut seen = std::collections::HashMap::new();
                    loop {
                        for (tid, name, cpu) in thread_cpu() {
                            let first = baseline.get(&tid).copied().unwrap_or(0.0);
                            let e = seen.entry(tid).or_insert((name.clone(), first, cpu));
                            e.0 = name;
                            e.2 = cpu;
                        }
                        if done.load(Ordering::Relaxed) {
                            return seen;
                        }
                        std::thread::sleep(std::time::Duration::from_millis(200));
                    }
                }
            })?;
        Ok(ThreadCpu {
            done,
            handle: Some(handle),
            started: std::time::Instant::now(),
        })
    }

    /// Stops; each thread name's CPU over the wall time since the start, percent of one core,
    /// largest first (threads of one name, e.g. per-client writers, added together).
    pub fn finish(mut self) -> Vec<(String, f64)> {
        self.done.store(true, std::sync::atomic::Ordering::Relaxed);
        let seen = self
            .handle
            .take()
            .and_then(|h| h.join().ok())
            .unwrap_or_default();
        let wall = self.started.elapsed().as_secs_f64().max(1e-9);
        let mut by_name: std::collections::BTreeMap<String, f64> = Default::default();
        for (name, first, last) in seen.into_values() {
            if name != "cpu-sampler" {
                *by_name.entry(name).or_default() += (last - first).max(0.0);
            }
        }
        let mut out: Vec<(String, f64)> = by_name
            .into_iter()
            .map(|(n, s)| (n, 100.0 * s / wall))
            .collect();
        out.sort_by(|a, b| b.1.total_cmp(&a.1));
        out
    }
}

/// The size of a memory page, bytes (4096 where `sysconf` cannot tell).
pub fn page_size() -> u64 {
    // SAFETY: sysconf only reads a system constant.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    u64::try_from(page).ok().filter(|&p| p > 0).unwrap_or(4096)
}

/// The address space the process takes, bytes (field 1 of `/proc/self/statm`); `None` where
/// /proc is missing.
pub fn virtual_bytes() -> Option<u64> {
    statm_bytes(0)
}

/// The process's resident set now, bytes (field 2 of `/proc/self/statm`); `None` where /proc is
/// missing.
pub fn resident_bytes() -> Option<u64> {
    statm_bytes(1)
}

/// Field `index` (from 0) of `/proc/self/statm`, pages, in bytes.
fn statm_bytes(index: usize) -> Option<u64> {
    let pages = std::fs::read_to_string("/proc/self/statm")
        .ok()?
        .split_whitespace()
        .nth(index)?
        .parse::<u64>()
        .ok()?;
    Some(pages * page_size())
}

/// Makes a write past the file-size limit (`ulimit -f`) fail with an error (`EFBIG`), as a full
/// disk does, instead of killing the process with `SIGXFSZ`: the command then says what it
/// wrote and where, like any other failed write.
pub fn file_size_limit_is_an_error() {
    // SAFETY: setting a signal's disposition to "ignore" installs no handler; nothing else
    // in the process handles SIGXFSZ.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn process_usage_is_read() {
        let u = ProcessUsage::now();
        assert!(u.max_rss_kib > 0);
        assert!(u.rss_kib > 0);
        assert!(page_size() >= 4096);
        let (virt, res) = (virtual_bytes().unwrap(), resident_bytes().unwrap());
        assert!(virt >= res && res > 0, "{virt} {res}");
    }
}

#[cfg(test)]
mod thread_tests {
    use super::*;

    #[test]
    fn a_busy_thread_shows_under_its_name() {
        let cpu = ThreadCpu::start().unwrap();
        std::thread::Builder::new()
            .name("busy-for-test".into())
            .spawn(|| {
                let start = std::time::Instant::now();
                let mut x = 0u64;
                while start.elapsed() < std::time::Duration::from_millis(1000) {
                    x = std::hint::black_box(x.wrapping_add(1));
                }
            })
            .unwrap()
            .join()
            .unwrap();
        let threads = cpu.finish();
        let busy = threads
            .iter()
            .find(|(n, _)| n == "busy-for-test")
            .map_or(0.0, |(_, p)| *p);
        // Ended before the last reading: kept with its last reading (taken every 200 ms).
        assert!(busy > 10.0, "{threads:?}");
        assert!(!threads.iter().any(|(n, _)| n == "cpu-sampler"));
    }
}
