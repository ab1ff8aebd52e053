//! Helpers shared by the integration tests that talk to the Python readers
//! (`tests/python/crosscheck.py`): where the interpreter is, temporary folders, receivers.
#![allow(dead_code)]

/// Prints a test's `SKIPPED ...` line where a plain `cargo test` shows it: on the process's own
/// standard error, which the test harness does not capture (it captures `eprintln!`).
#[macro_export]
macro_rules! skipped {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stderr(), $($arg)*);
    }};
}

pub mod batch;

use std::path::{Path, PathBuf};
use std::process::Command;

/// The project's Python interpreter (`V2CE_PYTHON`, else `.venv/bin/python`); `None` when
/// absent, unless `V2CE_REQUIRE_PYTHON` is set (CI), where absence fails the test.
pub fn python() -> Option<PathBuf> {
    let p = std::env::var_os("V2CE_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python"));
    if p.exists() {
        return Some(p);
    }
    if std::env::var_os("V2CE_REQUIRE_PYTHON").is_some() {
        panic!(
            "V2CE_REQUIRE_PYTHON is set but there is no interpreter at {}",
            p.display()
        );
    }
    None
}

#[macro_export]
/// The interpreter, or a printed reason and an early return from the test.
macro_rules! python_or_skip {
    ($test:literal) => {
        match $crate::common::python() {
            Some(p) => p,
            None => {
                skipped!(
                    "SKIPPED {}: no Python venv with faery/aedat/dv-processing (run .ci/run or set V2CE_PYTHON)",
                    $test
                );
                return;
            }
        }
    };
}

/// The cross-check script.
pub fn script() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/crosscheck.py")
}

/// A temporary folder for one test, removed with everything in it when dropped (kept when
/// `V2CE_KEEP_TEMP` is set, to look at after a failure): the suite writes gigabytes of models
/// and event files, which must not pile up run after run.
pub struct TempDir(PathBuf);

impl std::ops::Deref for TempDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for TempDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<std::ffi::OsStr> for TempDir {
    fn as_ref(&self) -> &std::ffi::OsStr {
        self.0.as_os_str()
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if std::env::var_os("V2CE_KEEP_TEMP").is_none() {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }
}

/// A fresh temporary folder for one test (see [`TempDir`]).
pub fn temp_dir(name: &str) -> TempDir {
    let d = std::env::temp_dir().join(format!("v2ce-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    TempDir(d)
}

/// Starts `crosscheck.py ARGS` and waits for its READY line.
pub fn start_receiver(py: &Path, args: &[String]) -> std::process::Child {
    use std::io::BufRead;
    let mut child = Command::new(py)
        .arg(script())
        .args(args)
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let stdout = child.stdout.take().unwrap();
    let mut lines = std::io::BufReader::new(stdout).lines();
    let first = lines.next().unwrap().unwrap();
    assert_eq!(first, "READY", "receiver said {first}");
    // Keep reading the rest in the background so the child never blocks on a full pipe.
    std::thread::spawn(move || {
        for line in lines.map_while(|l| l.ok()) {
            eprintln!("receiver: {line}");
        }
    });
    child
}

/// The recordings folder (`V2CE_DATA`, else ../shared/data), or the path looked at.
pub fn data_dir() -> Result<PathBuf, PathBuf> {
    let dir = std::env::var_os("V2CE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"));
    if dir.is_dir() {
        Ok(dir)
    } else {
        Err(dir)
    }
}

/// The recordings folder, or a printed reason and an early return from the test.
#[macro_export]
macro_rules! data_or_skip {
    ($test:literal) => {
        match $crate::common::data_dir() {
            Ok(d) => d,
            Err(d) => {
                skipped!(
                    "SKIPPED {}: no recordings at {} (set V2CE_DATA to the recordings folder)",
                    $test,
                    d.display()
                );
                return;
            }
        }
    };
}

/// A UDP port on loopback that nothing listens on now (bound, then released).
pub fn free_udp_port() -> u16 {
    std::net::UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}
