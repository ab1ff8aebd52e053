"""Runs the peer simulator eventcv (PyPI) on the APS frames of an AEDAT 4.0 recording (or the
frames of a frame list, as `v2ce reconstruct` writes for recordings without frames) and writes
its events as CSV (t_us,x,y,on) on the recording's clock, for `v2ce eval stage1`. Also times it.

    RAYON_NUM_THREADS=1 python tools/eventcv_peer.py REC.aedat4 OUT.csv [--noise] [--repeat N]
    RAYON_NUM_THREADS=1 python tools/eventcv_peer.py FRAMES/images.txt OUT.csv [--noise]
    RAYON_NUM_THREADS=1 python tools/eventcv_peer.py --npy FRAMES.npy FPS [--noise] [--repeat N]

The second form only times eventcv on uint8 frames [N, H, W] and prints `FPS <frames/s>`
(used by `cargo bench --bench stage1`).

Frames go to eventcv as the 8-bit APS values (which it linearises as sRGB), at the recording's
mean frame rate; event times are shifted so eventcv's time 0 is the first frame's mid-exposure.
"""

import sys
import time

import aedat
import numpy as np
import eventcv


def simulate_timed(frames, fps, noise, repeat):
    """eventcv's events for `frames` and its best wall time over `repeat` runs."""
    kwargs = {} if noise else dict(sigma_thres=0.0, leak_rate_hz=0.0, shot_noise_rate_hz=0.0)
    best, events = None, None
    for _ in range(repeat):
        start = time.perf_counter()
        events = eventcv.simulate(frames, fps=fps, **kwargs)
        took = time.perf_counter() - start
        best = took if best is None else min(best, took)
    return events, best


def read_aps(path):
    """The APS frames of an AEDAT 4.0 recording (uint8 [N, H, W]) and their mid-exposure times."""
    frames, times = [], []
    for packet in aedat.Decoder(path):
        if "frame" in packet:
            f = packet["frame"]
            frames.append(np.asarray(f["pixels"], dtype=np.uint8).reshape(f["height"], f["width"]))
            b, e = f["exposure_begin_t"], f["exposure_end_t"]
            times.append(b + (e - b) // 2 if e >= b > 0 else f["t"])
    return np.stack(frames), times


def read_frame_list(path):
    """The 8-bit gray images of a frame list (`t_seconds image_path` lines, as IJRR's
    images.txt) and their times in us (needs Pillow)."""
    from decimal import Decimal
    from pathlib import Path

    from PIL import Image

    frames, times = [], []
    base = Path(path).parent
    for line in Path(path).read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        t, name = line.split()[:2]
        times.append(int((Decimal(t) * 1_000_000).to_integral_value()))
        frames.append(np.asarray(Image.open(base / name).convert("L"), dtype=np.uint8))
    return np.stack(frames), times


def read_frames(path):
    """The frames (uint8 [N, H, W]) and their times (us) of an AEDAT 4.0 recording's APS stream
    or of a frame list (.txt)."""
    return read_frame_list(path) if path.endswith(".txt") else read_aps(path)


def time_npy(argv, noise, repeat):
    frames = np.load(argv[2])
    events, best = simulate_timed(frames, float(argv[3]), noise, repeat)
    print(f"FPS {len(frames) / best:.2f} EVENTS {len(events)}")


def main(argv):
    noise = "--noise" in argv
    repeat = int(argv[argv.index("--repeat") + 1]) if "--repeat" in argv else 1
    if argv[1] == "--npy":
        return time_npy(argv, noise, repeat)
    path, out = argv[1], argv[2]
    frames, times = read_frames(path)
    fps = 1e6 * (len(times) - 1) / (times[-1] - times[0])
    events, best = simulate_timed(frames, fps, noise, repeat)
    arr = np.asarray(eventcv.numpy(events))
    cols = list(events.columns)
    col = lambda *names: arr[:, [i for i, c in enumerate(cols) if c in names][0]]
    t = np.asarray(col("t", "timestamp", "ts"), dtype=np.int64) + times[0]
    x, y = col("x"), col("y")
    p = col("p", "polarity", "on")
    order = np.lexsort((p, x, y, t))
    rows = np.stack([t, x, y, (np.asarray(p) > 0).astype(np.int64)], axis=1)[order]
    np.savetxt(out, rows, fmt="%d", delimiter=",", header="t_us,x,y,on", comments="")
    print(
        f"eventcv {'with' if noise else 'without'} noise: {len(rows)} events, "
        f"{len(frames)} frames at {fps:.3f} fps, best of {repeat}: {best:.3f} s "
        f"({len(frames) / best:.1f} frames/s); columns {cols}"
    )


if __name__ == "__main__":
    main(sys.argv)
