#!/usr/bin/env python3
"""The "nothing lost" sweep (issue 47): several hundred hostile cases over every command that
writes a file, every signal during every output, a full disk under every writer, and every
reader of a format that declares sizes. Each case runs under an address-space limit and a
time limit and is judged: no abort, no hang, no input changed, no exit 0 with a failed
output, and every file left behind readable holding what the command said.

    python3 tools/sweep_nothing_lost.py [--v2ce target/release/v2ce] [--only KIND]

Standard library only. The full-disk cases mount a tmpfs (root); they are counted as
skipped, with the reason, where that is refused. Prints one line per failed case and a table
of counts per kind (docs/testing.md quotes it)."""

import argparse
import hashlib
import os
import re
import shutil
import signal
import stat
import struct
import subprocess
import sys
import tempfile
import time

MEMORY_KIB = 4_000_000  # the red team's 4 GB address-space cap
TIMEOUT_S = 120

RESULTS = {}  # kind -> [passed, failed, skipped]
FAILURES = []


def record(kind, case, ok, why=""):
    counts = RESULTS.setdefault(kind, [0, 0, 0])
    if ok is None:
        counts[2] += 1
        return
    counts[0 if ok else 1] += 1
    if not ok:
        FAILURES.append(f"{kind}: {case}: {why}")
        print(f"FAIL {kind}: {case}: {why}", flush=True)


def limited(args, timeout=TIMEOUT_S, **kw):
    """Runs `args` under the memory cap; returns (returncode, stderr) or (None, why) on a hang."""
    def cap():
        import resource
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_KIB * 1024, MEMORY_KIB * 1024))
    try:
        p = subprocess.run(args, capture_output=True, timeout=timeout, preexec_fn=cap, **kw)
    except subprocess.TimeoutExpired:
        return None, f"no end within {timeout} s"
    return p.returncode, p.stderr.decode(errors="replace")


def aborted(code):
    return code is None or code < 0 or code in (134, 137)


def digest(path):
    if not os.path.isfile(path):
        return None
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def events_of(v2ce, path):
    """The event count `v2ce info` reads in `path`, or None where it does not read."""
    p = subprocess.run([v2ce, "info", path], capture_output=True, timeout=TIMEOUT_S)
    if p.returncode != 0:
        return None
    m = re.search(rb"^events\s+(\d+)", p.stdout, re.M)
    return int(m.group(1)) if m else None


# --- 1. Where outputs go ------------------------------------------------------------------


def sweep_targets(v2ce, work):
    kind = "output targets"
    src = os.path.join(work, "in.csv")
    with open(src, "w") as f:
        f.write("t_us,x,y,on\n")
        for i in range(2000):
            f.write(f"{i * 50},{i % 40},{(i * 7) % 30},{i % 2}\n")
    other = os.path.join(work, "other.csv")
    shutil.copy(src, other)
    link = os.path.join(work, "link.csv")
    os.symlink(src, link)
    fifo = os.path.join(work, "fifo.csv")
    os.mkfifo(fifo)
    folder = os.path.join(work, "folder.csv")
    os.mkdir(folder)
    existing = os.path.join(work, "existing.csv")
    shutil.copy(src, existing)
    original = {p: digest(p) for p in (src, other, existing)}
    # Each command, and the files among those above that it reads.
    commands = {
        "transcode": (lambda out: ["transcode", src, out], {src}),
        "convert": (lambda out: ["convert", "fixture", "--max-frames", "3", "-o", out], set()),
        "repair --out": (lambda out: ["repair", src, "--out", out], {src}),
        "calibrate": (lambda out: ["calibrate", "--real", src, "-o", out, "--max-frames", "3"],
                      {src}),
        "eval realism --plot": (lambda out: ["eval", "realism", "--real", src, "--sim", other,
                                             "--fps", "100", "--plot", out], {src, other}),
        "eval stage2 --write-events": (lambda out: ["eval", "stage2", "--events", src, "--fps",
                                                    "100", "--write-events", out], {src}),
        "render": (lambda out: ["render", src, "--output", out], {src}),
        "listen -o": (lambda out: ["listen", "--udp", "127.0.0.1:0", "--duration", "0.3",
                                   "-o", out], set()),
    }
    # Each target, and the file it is (None: not a regular file of ours).
    targets = {
        "the input": (src, src),
        "the input through a link": (link, src),
        "the input spelled ./": (os.path.join(work, ".", "in.csv"), src),
        "the other input": (other, other),
        "/dev/null": ("/dev/null", None),
        "/dev/full": ("/dev/full", None),
        "a FIFO": (fifo, None),
        "a directory": (folder, None),
        "an existing file": (existing, existing),
        "a missing folder": (os.path.join(work, "missing", "out.csv"), None),
    }
    for name, (command, reads) in commands.items():
        for target, (path, file) in targets.items():
            for force in ([], ["--force"]):
                code, err = limited([v2ce] + command(path) + force, timeout=60)
                case = f"{name} -> {target} {' '.join(force)}".strip()
                # Replacing a file is right only with --force and where the command does not
                # read it.
                may_replace = bool(force) and file is not None and file not in reads
                changed = [p for p, d in original.items() if digest(p) != d]
                kept = (stat.S_ISCHR(os.stat("/dev/null").st_mode)
                        and stat.S_ISCHR(os.stat("/dev/full").st_mode)
                        and stat.S_ISFIFO(os.stat(fifo).st_mode)
                        and os.path.isdir(folder))
                if aborted(code):
                    record(kind, case, False, f"aborted or hung ({code}): {err[-300:]}")
                elif any(p in reads or not may_replace for p in changed):
                    record(kind, case, False, f"changed {changed}")
                elif not kept:
                    record(kind, case, False, "a device, FIFO or folder was replaced")
                elif code == 0 and not may_replace:
                    record(kind, case, False, f"exit 0 writing to {target}")
                elif code != 0 and "error" not in err:
                    record(kind, case, False, f"exit {code} without an error: {err[-200:]}")
                else:
                    record(kind, case, True)
                for p in changed:
                    shutil.copy(other if p != other else src, p)
                    if p == other:
                        shutil.copy(src, other)
                # A link replaced where that was right (a command that does not read it).
                if not os.path.islink(link):
                    os.remove(link)
                    os.symlink(src, link)


# --- 2. A full disk --------------------------------------------------------------------------


FORMATS = [("csv", None), ("raw", "2"), ("raw", "3"), ("aedat4", None), ("npz", None),
           ("h5", None), ("mcap", None)]


def mount_tmpfs(path, size):
    os.makedirs(path, exist_ok=True)
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", path],
                       capture_output=True)
    return p.returncode == 0, p.stderr.decode(errors="replace").strip()


def closed_with(err):
    m = re.search(r"; ([^;]+) was closed readably with the (\d+) events", err)
    return (m.group(1), int(m.group(2))) if m else (None, None)


def judge_full_disk(v2ce, kind, case, code, err, out, failure):
    """A command that wrote `out` on a small disk: exit 0 only with a whole file; else an
    error saying `failure`, and the file it names holding the count it says (none named where
    it failed before any event: its header did not fit)."""
    path, n = closed_with(err)
    if aborted(code):
        record(kind, case, False, f"aborted or hung: {err[-300:]}")
    elif code == 0:
        record(kind, case, events_of(v2ce, out) is not None, "unreadable")
    elif failure not in err:
        record(kind, case, False, f"exit {code} without saying '{failure}': {err[-300:]}")
    elif path is None:
        record(kind, case, True)
    else:
        got = events_of(v2ce, path)
        record(kind, case, got == n, f"{path} holds {got}, said {n}")


def sweep_full_disk(v2ce, work):
    kind = "full disk"
    source = os.path.join(work, "source.aedat4")
    subprocess.run([v2ce, "convert", "fixture", "--max-frames", "60", "-o", source,
                    "--force"], capture_output=True, check=True)
    disk = os.path.join(work, "disk")
    for size in ["256k", "1m", "3m"]:
        ok, why = mount_tmpfs(disk, size)
        if not ok:
            for _ in range(len(FORMATS) * 4):
                record(kind, "", None)
            print(f"SKIPPED the full-disk cases at {size}: {why}")
            continue
        try:
            for ext, evt in FORMATS:
                whole = os.path.join(work, f"whole-{evt or ''}.{ext}")
                extra = ["--evt", evt] if evt else []
                subprocess.run([v2ce, "transcode", source, whole, "--force"] + extra,
                               capture_output=True, check=True)
                runs = {
                    "convert": ["convert", "fixture", "--max-frames", "60"] + extra + ["-o"],
                    "transcode": ["transcode", source] + extra,
                    "repair --out": ["repair", whole, "--out"],
                }
                for name, args in runs.items():
                    if name == "repair --out" and ext in ("npz", "h5"):
                        continue
                    for f in os.listdir(disk):
                        os.remove(os.path.join(disk, f))
                    out = os.path.join(disk, f"f.{ext}")
                    code, err = limited([v2ce] + args + [out])
                    case = f"{name} .{ext} {evt or ''} on {size}"
                    judge_full_disk(v2ce, kind, case, code, err, out, "space")
                # run: the file output fails while the UDP output goes on.
                for f in os.listdir(disk):
                    os.remove(os.path.join(disk, f))
                out = os.path.join(disk, f"r.{ext}")
                config = os.path.join(work, "run.toml")
                with open(config, "w") as f:
                    f.write(f'[[sink]]\ntype = "file"\npath = "{out}"\nevt = {evt or 2}\n')
                code, err = limited([v2ce, "run", "--source", "fixture", "--max-frames", "60",
                                     "--udp", "127.0.0.1:9", "--queue-policy", "block",
                                     "--replay-speed", "8", "--config", config])
                case = f"run .{ext} {evt or ''} on {size}"
                judge_full_disk(v2ce, kind, case, code, err, out, "output(s) failed")
        finally:
            subprocess.run(["umount", disk], capture_output=True)


# --- 3. Signals during outputs ---------------------------------------------------------------


def sweep_signals(v2ce, work):
    kind = "signals"
    folder = os.path.join(work, "signals")
    os.makedirs(folder, exist_ok=True)
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        for ext, evt in FORMATS:
            extra = ["--evt", evt] if evt else []
            for delay in (0.3, 1.5):
                # run: a clean stop, exit 0, its file whole with the count it says.
                out = os.path.join(folder, f"run-{sig.name}-{delay}-{evt or ''}.{ext}")
                config = os.path.join(folder, "run.toml")
                with open(config, "w") as f:
                    f.write(f'[[sink]]\ntype = "file"\npath = "{out}"\nevt = {evt or 2}\n')
                p = subprocess.Popen([v2ce, "run", "--source", "fixture", "--loop", "--udp",
                                      "127.0.0.1:9", "--config", config],
                                     stderr=subprocess.PIPE)
                time.sleep(delay)
                p.send_signal(sig)
                case = f"run .{ext} {evt or ''} {sig.name} after {delay} s"
                try:
                    _, err = p.communicate(timeout=60)
                except subprocess.TimeoutExpired:
                    p.kill()
                    record(kind, case, False, "no stop within 60 s")
                    continue
                err = err.decode(errors="replace")
                m = re.search(r"file [^\n]*?\): (\d+) events sent", err)
                got = events_of(v2ce, out) if os.path.exists(out) else 0
                if p.returncode != 0:
                    record(kind, case, False, f"exit {p.returncode}: {err[-300:]}")
                elif m and got != int(m.group(1)):
                    record(kind, case, False, f"holds {got}, said {m.group(1)}")
                else:
                    record(kind, case, got is not None, "unreadable")
            # convert: exit 130 (stopped before the input ended) or 0 (it had ended), the
            # file (partial or whole) readable.
            out = os.path.join(folder, f"conv-{sig.name}-{evt or ''}.{ext}")
            partial = out[: -len(ext) - 1] + ".partial." + ext
            p = subprocess.Popen([v2ce, "convert", "fixture", "--size", "1280x960", "-o", out,
                                  "--force"] + extra, stderr=subprocess.PIPE,
                                 env=dict(os.environ, V2CE_THREADS="1"))
            time.sleep(1.5)
            p.send_signal(sig)
            case = f"convert .{ext} {evt or ''} {sig.name}"
            try:
                _, err = p.communicate(timeout=120)
            except subprocess.TimeoutExpired:
                p.kill()
                record(kind, case, False, "no stop within 120 s")
                continue
            left = partial if p.returncode == 130 else out
            if p.returncode not in (0, 130):
                record(kind, case, False, f"exit {p.returncode}: {err[-300:]}")
            else:
                record(kind, case, events_of(v2ce, left) is not None, f"{left} unreadable")
        # listen: a clean stop with its report, its file whole.
        for ext, evt in FORMATS:
            if evt == "3":
                continue
            out = os.path.join(folder, f"listen-{sig.name}.{ext}")
            p = subprocess.Popen([v2ce, "listen", "--udp", "127.0.0.1:0", "-o", out,
                                  "--force"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            line = p.stdout.readline().decode()
            port = re.search(r":(\d+)", line)
            case = f"listen -o .{ext} {sig.name}"
            if port:
                sender = subprocess.Popen([v2ce, "run", "--source", "fixture", "--loop",
                                           "--udp", f"127.0.0.1:{port.group(1)}"],
                                          stderr=subprocess.DEVNULL)
                time.sleep(1.5)
            p.send_signal(sig)
            try:
                _, err = p.communicate(timeout=60)
            except subprocess.TimeoutExpired:
                p.kill()
                record(kind, case, False, "no stop within 60 s")
                continue
            finally:
                if port:
                    sender.terminate()
                    sender.wait()
            err = err.decode(errors="replace")
            got = events_of(v2ce, out)
            record(kind, case, p.returncode == 0 and got is not None,
                   f"exit {p.returncode}, {got} events: {err[-300:]}")


# --- 4. Readers of formats that declare sizes ------------------------------------------------


def mutations(v2ce, work):
    """(name, path) of hostile files: size fields of each format set to absurd values."""
    out = []
    base = os.path.join(work, "readers")
    os.makedirs(base, exist_ok=True)
    src = os.path.join(work, "readers-source.aedat4")
    subprocess.run([v2ce, "convert", "fixture", "--max-frames", "10", "-o", src, "--force"],
                   capture_output=True, check=True)
    files = {}
    for ext, evt in FORMATS:
        p = os.path.join(base, f"good-{evt or ''}.{ext}")
        subprocess.run([v2ce, "transcode", src, p, "--force"] + (["--evt", evt] if evt else []),
                       capture_output=True, check=True)
        with open(p, "rb") as f:
            files[(ext, evt)] = f.read()
    values = [0, 1, 0x7FFF_FFFF, 0xFFFF_FFFF]

    def write(name, data, ext):
        path = os.path.join(base, f"{name}.{ext}")
        with open(path, "wb") as f:
            f.write(data)
        out.append((name, path))

    # AEDAT 4.0: the IOHeader's size, the first packet's stream id and size.
    a = files[("aedat4", None)]
    magic = 14
    header = struct.unpack_from("<I", a, magic)[0]
    first = magic + 4 + header
    for v in values:
        b = bytearray(a)
        struct.pack_into("<I", b, magic, v)
        write(f"aedat4-header-{v}", b, "aedat4")
        b = bytearray(a)
        struct.pack_into("<I", b, first + 4, v)
        write(f"aedat4-packet-{v}", b, "aedat4")
        b = bytearray(a[: first + 8 + 100])
        struct.pack_into("<I", b, first + 4, v)
        write(f"aedat4-packet-cut-{v}", b, "aedat4")
    # RAW: the header's geometry and format lines.
    for evt in ("2", "3"):
        r = files[("raw", evt)]
        end = r.find(b"% end\n")
        body = r[end + 6:] if end >= 0 else r
        for geometry in ["0x0", "65535x65535", "99999999x99999999", "-5x7", "x"]:
            head = f"% evt {evt}.0\n% geometry {geometry}\n% format EVT{evt}\n% end\n"
            write(f"raw{evt}-geometry-{geometry}", head.encode() + body, "raw")
        write(f"raw{evt}-header-only", r[: end + 6], "raw")
        write(f"raw{evt}-odd", r + b"\x01", "raw")
    # NPZ: the .npy header's shape, the zip entry's sizes.
    n = files[("npz", None)]
    for shape in ["(1000000000000,)", "(-1,)", "(99999999999999999999,)", "(3, 4)", "()"]:
        # The same length (the padding gives or takes), so the archive's offsets hold.
        old = re.search(rb"'shape': \([^)]*\), \}( *)\n", n)
        text = f"'shape': {shape}, }}".encode()
        pad = len(old.group(0)) - 1 - len(text)
        b = n[: old.start()] + text + b" " * pad + b"\n" + n[old.end():]
        write(f"npz-shape-{shape}", b, "npz")
    for v in values:
        b = bytearray(n)
        struct.pack_into("<I", b, 18, v)  # the local header's compressed size
        struct.pack_into("<I", b, 22, v)  # and uncompressed size
        write(f"npz-local-size-{v}", b, "npz")
        at = n.rfind(b"PK\x01\x02")
        if at >= 0:
            b = bytearray(n)
            struct.pack_into("<I", b, at + 20, v)
            struct.pack_into("<I", b, at + 24, v)
            write(f"npz-central-size-{v}", b, "npz")
    # CSV: a header only, a line longer than any reader takes, no newline at all.
    write("csv-header-only", b"t_us,x,y,on\n", "csv")
    write("csv-long-line", b"t_us,x,y,on\n" + b"1" * (64 << 20), "csv")
    write("csv-columns-absurd", b"t,x,y,p\n1e300,1,1,1\n", "csv")
    # Y4M frames: absurd sizes (a frame reader).
    for w, h in [(0, 0), (99999, 99999), (8193, 1), (65536, 65536)]:
        write(f"y4m-{w}x{h}", f"YUV4MPEG2 W{w} H{h} F30:1 C420jpeg\nFRAME\n".encode()
              + b"\0" * 1000, "y4m")
    return out


def sweep_readers(v2ce, work):
    kind = "readers of declared sizes"
    for name, path in mutations(v2ce, work):
        outs = os.path.join(work, "reader-out")
        os.makedirs(outs, exist_ok=True)
        if path.endswith(".y4m"):
            commands = [["convert", path, "-o", os.path.join(outs, "o.csv"), "--force"],
                        ["info", path]]
        else:
            commands = [["info", path],
                        ["transcode", path, os.path.join(outs, "o.csv"), "--force"],
                        ["repair", path, "--out", os.path.join(outs, "r" + os.path.splitext(
                            path)[1]), "--force"],
                        ["render", path, "--output", os.path.join(outs, "o.png"), "--force"]]
        before = digest(path)
        for args in commands:
            code, err = limited([v2ce] + args)
            case = f"{args[0]} {name}"
            if aborted(code):
                record(kind, case, False, f"aborted or hung ({code}): {err[-300:]}")
            elif digest(path) != before:
                record(kind, case, False, "the input changed")
            elif code != 0 and "error" not in err:
                record(kind, case, False, f"exit {code} without an error: {err[-200:]}")
            else:
                record(kind, case, True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--v2ce", default="target/release/v2ce")
    ap.add_argument("--only", choices=["targets", "disk", "signals", "readers"])
    a = ap.parse_args()
    v2ce = os.path.abspath(a.v2ce)
    work = tempfile.mkdtemp(prefix="v2ce-sweep-")
    started = time.time()
    try:
        for name, sweep in [("targets", sweep_targets), ("disk", sweep_full_disk),
                            ("signals", sweep_signals), ("readers", sweep_readers)]:
            if a.only in (None, name):
                sweep(v2ce, work)
    finally:
        subprocess.run(["umount", os.path.join(work, "disk")], capture_output=True)
        shutil.rmtree(work, ignore_errors=True)
    print()
    print(f"| kind | cases | passed | failed | skipped |")
    print(f"|---|---:|---:|---:|---:|")
    total = [0, 0, 0]
    for kind, (p, f, s) in RESULTS.items():
        print(f"| {kind} | {p + f + s} | {p} | {f} | {s} |")
        total = [total[0] + p, total[1] + f, total[2] + s]
    print(f"| all | {sum(total)} | {total[0]} | {total[1]} | {total[2]} |")
    print(f"\n{time.time() - started:.0f} s")
    return 1 if FAILURES else 0


if __name__ == "__main__":
    sys.exit(main())
