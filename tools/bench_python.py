"""Times the Python package (issue 26) in one run, as ratios: the binding against the CLI on the
same conversion, `v2ce.convert` on numpy frames against eventcv's Python API on the same frames,
and `v2ce.read` against faery and expelliarmus on a large file. Medians of `--repeat` runs.

    .venv/bin/python tools/bench_python.py [--repeat 3] [--cli target/release/v2ce]
        [--aps ../shared/data/davis346/davis346.aedat4]
"""

import argparse
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import v2ce


def median_time(f, repeat):
    times, out = [], None
    for _ in range(repeat):
        start = time.perf_counter()
        out = f()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def aps_frames(path):
    import aedat

    frames, times = [], []
    for packet in aedat.Decoder(str(path)):
        if "frame" in packet:
            f = packet["frame"]
            frames.append(np.asarray(f["pixels"], np.uint8).reshape(f["height"], f["width"]))
            b, e = f["exposure_begin_t"], f["exposure_end_t"]
            times.append(b + (e - b) // 2 if e >= b > 0 else f["t"])
    return np.stack(frames), np.asarray(times, np.int64)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cli", default="target/release/v2ce")
    ap.add_argument("--aps", default="../shared/data/davis346/davis346.aedat4")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp())

    # 1. The binding's cost over the CLI: the fixture (180 frames, 640x480), same settings.
    out = tmp / "cli.aedat4"
    cli_s, _ = median_time(
        lambda: subprocess.run([a.cli, "convert", "fixture", "-o", str(out), "--force"],
                               check=True, capture_output=True), a.repeat)
    py_s, events = median_time(lambda: v2ce.convert("fixture"), a.repeat)
    print(f"fixture: CLI {cli_s:.2f} s, v2ce.convert {py_s:.2f} s "
          f"({len(events)} events): binding/CLI {py_s / cli_s:.3f}")

    # 2. Numpy frames against eventcv's Python API (the davis346 APS frames, uint8).
    if Path(a.aps).exists():
        frames, times = aps_frames(a.aps)
        fps = 1e6 * (len(times) - 1) / (times[-1] - times[0])
        ours_s, ours = median_time(lambda: v2ce.convert(frames, times_us=times), a.repeat)
        try:
            import eventcv

            peer_s, peer = median_time(lambda: eventcv.simulate(frames, fps=fps), a.repeat)
            print(f"{len(frames)} APS frames {frames.shape[2]}x{frames.shape[1]}: v2ce.convert "
                  f"{ours_s:.3f} s ({len(ours)} events), eventcv.simulate {peer_s:.3f} s "
                  f"({len(peer)} events): v2ce/eventcv {ours_s / peer_s:.3f}")
        except ImportError:
            print(f"v2ce.convert on {len(frames)} APS frames: {ours_s:.3f} s (eventcv absent)")
    else:
        print(f"no {a.aps}: numpy frames against eventcv not measured")

    # 3. Reading a large file: the fixture's events as EVT 2.0.
    raw = tmp / "big.raw"
    v2ce.write(raw, events, v2ce.size_of(events))
    ours_s, got = median_time(lambda: v2ce.read(raw), a.repeat)
    line = f"read {len(got)} events from EVT 2.0 ({raw.stat().st_size / 1e6:.0f} MB): v2ce.read {ours_s:.3f} s"
    try:
        import faery

        s, _ = median_time(lambda: faery.events_stream_from_file(raw).to_array(), a.repeat)
        line += f", faery {s:.3f} s (v2ce/faery {ours_s / s:.2f})"
    except ImportError:
        pass
    try:
        import expelliarmus

        w = expelliarmus.Wizard(encoding="evt2")
        s, _ = median_time(lambda: w.read(str(raw)), a.repeat)
        line += f", expelliarmus {s:.3f} s (v2ce/expelliarmus {ours_s / s:.2f})"
    except ImportError:
        pass
    print(line)


if __name__ == "__main__":
    main()
