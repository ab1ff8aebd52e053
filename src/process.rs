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
