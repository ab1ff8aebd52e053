//! `v2ce batch` under a real Slurm: the test starts a one-node cluster on this machine (munged,
//! slurmctld and slurmd from Debian's `munge` and `slurm-wlm`, as root, with a generated key and
//! config in a temporary folder), submits `deploy/slurm/convert.sbatch` as an array of 4 over a
//! manifest of 9 inputs (one a corrupt video), checks every output and the merged report,
//! cancels one array task of a second run in the middle and submits again, and stops the
//! daemons by their PIDs at the end.
//!
//! It needs root and the packages; without them it prints why it skips, unless
//! `V2CE_REQUIRE_SLURM` is set (as `.ci/run` does as root), where their absence fails.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output};
use std::time::{Duration, Instant};

use common::batch::{assert_identical_to_convert, dataset, ledger, partials, text, v2ce};

/// The daemons of a one-node cluster, stopped (by PID) when dropped.
struct Cluster {
    conf: PathBuf,
    daemons: Vec<(&'static str, Child)>,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        // slurmd first (it runs the jobs), then slurmctld, then munged.
        for (name, child) in self.daemons.iter_mut().rev() {
            unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
            let deadline = Instant::now() + Duration::from_secs(10);
            while child.try_wait().ok().flatten().is_none() {
                if Instant::now() > deadline {
                    eprintln!("{name} ignored SIGTERM: killed");
                    let _ = child.kill();
                    let _ = child.wait();
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
}

fn which(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")?
        .to_string_lossy()
        .split(':')
        .chain(["/usr/sbin", "/sbin"])
        .map(|d| Path::new(d).join(name))
        .find(|p| p.is_file())
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

impl Cluster {
    /// Why this machine cannot run the cluster, if it cannot.
    fn missing() -> Option<String> {
        if unsafe { libc::geteuid() } != 0 {
            return Some("not root (slurmd and munged run as root here)".into());
        }
        let absent: Vec<&str> = [
            "munged",
            "slurmctld",
            "slurmd",
            "sbatch",
            "squeue",
            "scancel",
        ]
        .into_iter()
        .filter(|b| which(b).is_none())
        .collect();
        (!absent.is_empty()).then(|| {
            format!(
                "{} not installed (apt install slurm-wlm munge)",
                absent.join(", ")
            )
        })
    }

    fn start(dir: &Path) -> Cluster {
        let host = String::from_utf8(Command::new("hostname").arg("-s").output().unwrap().stdout)
            .unwrap()
            .trim()
            .to_string();
        let m = dir.join("munge");
        std::fs::create_dir_all(&m).unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&m, std::fs::Permissions::from_mode(0o711)).unwrap();
        let mut random = vec![0u8; 1024];
        use std::io::Read;
        std::fs::File::open("/dev/urandom")
            .unwrap()
            .read_exact(&mut random)
            .unwrap();
        let key = m.join("munge.key");
        std::fs::write(&key, &random).unwrap();
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
        let socket = m.join("munge.sock");
        let log = |name: &str| std::fs::File::create(dir.join(name)).unwrap();
        let munged = Command::new(which("munged").unwrap())
            .args(["-F", "-f"])
            .arg(format!("--key-file={}", key.display()))
            .arg(format!("--socket={}", socket.display()))
            .arg(format!("--pid-file={}", m.join("munged.pid").display()))
            .arg(format!("--log-file={}", m.join("munged.log").display()))
            .arg(format!("--seed-file={}", m.join("munged.seed").display()))
            .stdout(log("munged.out"))
            .stderr(log("munged.err"))
            .spawn()
            .unwrap();
        let mut cluster = Cluster {
            conf: dir.join("slurm.conf"),
            daemons: vec![("munged", munged)],
        };
        wait_for(Duration::from_secs(20), "munged's socket", || {
            socket.exists()
        });
        for d in ["state", "spool"] {
            std::fs::create_dir_all(dir.join(d)).unwrap();
        }
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        let p = |name: &str| dir.join(name).display().to_string();
        let conf = format!(
            "ClusterName=v2ce\nSlurmctldHost={host}\nSlurmUser=root\nSlurmdUser=root\n\
             SlurmctldPort={}\nSlurmdPort={}\nAuthType=auth/munge\nCredType=cred/munge\n\
             AuthInfo=socket={}\nProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\n\
             SelectType=select/cons_tres\nSelectTypeParameters=CR_CPU\n\
             SchedulerType=sched/backfill\nStateSaveLocation={}\nSlurmdSpoolDir={}\n\
             SlurmctldPidFile={}\nSlurmdPidFile={}\nSlurmctldLogFile={}\nSlurmdLogFile={}\n\
             ReturnToService=2\nMpiDefault=none\nJobCompType=jobcomp/none\n\
             AccountingStorageType=accounting_storage/none\n\
             JobAcctGatherType=jobacct_gather/none\nKillWait=5\n\
             NodeName={host} CPUs={cpus} State=UNKNOWN\n\
             PartitionName=debug Nodes={host} Default=YES MaxTime=INFINITE State=UP\n",
            free_port(),
            free_port(),
            socket.display(),
            p("state"),
            p("spool"),
            p("slurmctld.pid"),
            p("slurmd.pid"),
            p("slurmctld.log"),
            p("slurmd.log"),
        );
        std::fs::write(&cluster.conf, conf).unwrap();
        let ctld = Command::new(which("slurmctld").unwrap())
            .args(["-D", "-i", "-f"])
            .arg(&cluster.conf)
            .stdout(log("slurmctld.out"))
            .stderr(log("slurmctld.err"))
            .spawn()
            .unwrap();
        cluster.daemons.push(("slurmctld", ctld));
        let slurmd = Command::new(which("slurmd").unwrap())
            .args(["-D", "-f"])
            .arg(&cluster.conf)
            .stdout(log("slurmd.out"))
            .stderr(log("slurmd.err"))
            .spawn()
            .unwrap();
        cluster.daemons.push(("slurmd", slurmd));
        wait_for(Duration::from_secs(60), "the node to be idle", || {
            cluster
                .cmd("sinfo", &["-h", "-o", "%T"])
                .is_some_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "idle")
        });
        cluster
    }

    /// Runs a Slurm client command against this cluster.
    fn cmd(&self, name: &str, args: &[&str]) -> Option<Output> {
        Command::new(which(name)?)
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .output()
            .ok()
    }

    /// Submits the array job over `dir/list.txt` into `dir/out`; returns the job id.
    fn submit(&self, dir: &Path, out: &str, wait: bool) -> (String, Output) {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/slurm/convert.sbatch");
        let export = format!(
            "ALL,MANIFEST={},OUT={},V2CE={}",
            dir.join("list.txt").display(),
            dir.join(out).display(),
            env!("CARGO_BIN_EXE_v2ce")
        );
        let chdir = format!("--chdir={}", dir.display());
        let mut args = vec![
            "--parsable",
            "--array=0-3",
            "--cpus-per-task=1",
            "--export",
            &export,
            &chdir,
        ];
        if wait {
            args.push("--wait");
        }
        let script = script.display().to_string();
        args.push(&script);
        let o = self.cmd("sbatch", &args).unwrap();
        let id = String::from_utf8_lossy(&o.stdout)
            .trim()
            .split(';')
            .next()
            .unwrap_or("")
            .to_string();
        assert!(!id.is_empty(), "sbatch: {}", text(&o));
        (id, o)
    }

    /// The job's array tasks still queued or running.
    fn tasks(&self, job: &str, state: &str) -> Vec<String> {
        let o = self
            .cmd("squeue", &["-h", "-r", "-j", job, "-t", state, "-o", "%i"])
            .unwrap();
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .map(|l| l.trim().to_string())
            .filter(|l| !l.is_empty())
            .collect()
    }
}

fn wait_for(limit: Duration, what: &str, mut ok: impl FnMut() -> bool) {
    let started = Instant::now();
    while !ok() {
        assert!(started.elapsed() < limit, "waited {limit:?} for {what}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn a_slurm_job_array_converts_a_dataset_and_resumes_a_cancelled_task() {
    if let Some(why) = Cluster::missing() {
        assert!(
            std::env::var_os("V2CE_REQUIRE_SLURM").is_none(),
            "V2CE_REQUIRE_SLURM is set, but: {why}"
        );
        skipped!(
            "SKIPPED a_slurm_job_array_converts_a_dataset_and_resumes_a_cancelled_task: {why}"
        );
        return;
    }
    let dir = common::temp_dir("slurm");
    let cluster = Cluster::start(&dir);

    // An array of 4 over 9 inputs, one corrupt.
    let data = dir.join("small");
    dataset(&data, 8, 160, 120, |i| 20 + 10 * i);
    let (job, o) = cluster.submit(&data, "out", true);
    // The task with the corrupt input exits 1, so the array as a whole reports failure.
    assert!(!o.status.success(), "{}", text(&o));
    assert_identical_to_convert(&data, "out", 8);
    let records = ledger(&data, "out");
    for i in 0..8 {
        let name = format!("clips/c{i}.aedat4");
        assert_eq!(
            records.iter().filter(|(o, _)| *o == name).count(),
            1,
            "{name}: {records:?}"
        );
    }
    assert!(records.contains(&("clips/bad.aedat4".into(), "failed".into())));
    let logs: String = (0..4)
        .map(|t| {
            std::fs::read_to_string(data.join(format!("v2ce-convert-{job}_{t}.log")))
                .unwrap_or_default()
        })
        .collect();
    assert_eq!(logs.matches("FAILED").count(), 1, "{logs}");
    let o = v2ce(&["batch", "--report", "out", "list.txt", "--json"], &data);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["done"], 8);
    assert_eq!(r["failed"][0][0], "clips/bad.y4m");
    assert_eq!(r["shards"].as_object().unwrap().len(), 4, "{r}");
    let frames: u64 = (0..8).map(|i| 20 + 10 * i as u64).sum();
    assert_eq!(r["frames"], frames);
    // A second dataset at 320 x 240 (UCF101's size): the array's throughput against the same
    // inputs one after another (printed; the README quotes a run).
    let data = dir.join("big");
    dataset(&data, 8, 320, 240, |_| 120);
    cluster.submit(&data, "timed", true);
    let o = v2ce(&["batch", "--report", "timed", "--json"], &data);
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r["done"], 8, "{r}");
    let o = v2ce(
        &[
            "batch", "list.txt", "--out", "seq", "--shard", "0/1", "--jobs", "1", "--json",
        ],
        &data,
    );
    let seq: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    eprintln!(
        "slurm array of 4 tasks (1 CPU each) on {} CPUs, {} frames at 320x240: {:.1} frames/s per \
         task, {:.1} frames/s for the whole array (first start to last output); one after another \
         in one process: {:.1} frames/s",
        std::thread::available_parallelism().map_or(1, |n| n.get()),
        r["frames"],
        r["frames_per_busy_s"].as_f64().unwrap_or(0.0),
        r["frames_per_s"].as_f64().unwrap_or(0.0),
        seq["frames"].as_f64().unwrap_or(0.0) / seq["wall_s"].as_f64().unwrap_or(1.0)
    );

    // One array task cancelled while it writes, then the job submitted again.
    let (job, _) = cluster.submit(&data, "out", false);
    wait_for(Duration::from_secs(300), "a task writing an output", || {
        !partials(&data.join("out")).is_empty() || cluster.tasks(&job, "PD,R").is_empty()
    });
    let running = cluster.tasks(&job, "R");
    assert!(
        !running.is_empty(),
        "the job ended before a task could be cancelled"
    );
    let victim = running[0].clone();
    let o = cluster.cmd("scancel", &[&victim]).unwrap();
    assert!(o.status.success(), "{}", text(&o));
    wait_for(Duration::from_secs(300), "the first job to end", || {
        cluster.tasks(&job, "PD,R,CG").is_empty()
    });
    let before = ledger(&data, "out");
    let (_, o) = cluster.submit(&data, "out", true);
    // The corrupt input fails again; everything else is complete.
    assert!(!o.status.success(), "{}", text(&o));
    assert!(
        partials(&data.join("out"))
            .iter()
            .all(|p| p.contains("bad.partial")),
        "{:?}",
        partials(&data.join("out"))
    );
    let after = ledger(&data, "out");
    for i in 0..8 {
        let name = format!("clips/c{i}.aedat4");
        let done = after
            .iter()
            .filter(|(o, s)| *o == name && s == "done")
            .count();
        assert_eq!(done, 1, "{name} converted {done} times: {after:?}");
    }
    assert!(
        before.iter().filter(|(_, s)| s == "done").count() < 8,
        "the cancelled task had nothing left to do: {before:?}"
    );
    eprintln!(
        "cancelled {victim}: {} of 8 done before, all 8 after the resubmission",
        before.iter().filter(|(_, s)| s == "done").count()
    );
    assert_identical_to_convert(&data, "out", 8);
    drop(cluster);
}
