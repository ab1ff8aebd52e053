"""The naive frame-difference baseline: events from the log difference of consecutive APS
frames of an AEDAT 4.0 recording, every event stamped at the frame that showed it, written as
CSV (t_us,x,y,on) on the recording's clock, for `v2ce eval stage1` and `v2ce eval realism`.

    python tools/naive_peer.py REC.aedat4 OUT.csv [--threshold C]
    python tools/naive_peer.py FRAMES/images.txt OUT.csv [--threshold C]

Each pixel keeps the log level of its last event (the first frame's at the start); at each frame
it fires floor(|log(v) - level| / C) events of the sign of the difference, all at the frame's
mid-exposure time, and moves its level by that many thresholds. `v` is the 8-bit APS value
linearised as sRGB (as eventcv takes it), plus 1/255 so black has a log. No noise, no
refractory period, no bandwidth: what a simulator without a pixel model gives.
"""

import sys

import numpy as np

from eventcv_peer import read_frames


def linear(frames):
    """8-bit sRGB values as linear light in (0, 1]."""
    v = frames.astype(np.float64) / 255.0
    lin = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    return lin + 1.0 / 255.0


def main(argv):
    path, out = argv[1], argv[2]
    c = float(argv[argv.index("--threshold") + 1]) if "--threshold" in argv else 0.26
    frames, times = read_frames(path)
    logs = np.log(linear(frames))
    level = logs[0].copy()
    h, w = level.shape
    ys, xs = np.mgrid[0:h, 0:w]
    rows = []
    for k in range(1, len(frames)):
        diff = logs[k] - level
        n = np.floor(np.abs(diff) / c).astype(np.int64)
        on = diff > 0
        fire = n > 0
        counts = n[fire]
        x = np.repeat(xs[fire], counts)
        y = np.repeat(ys[fire], counts)
        p = np.repeat(on[fire], counts).astype(np.int64)
        t = np.full(len(x), times[k], dtype=np.int64)
        rows.append(np.stack([t, x, y, p], axis=1))
        level += np.sign(diff) * n * c
    rows = np.concatenate(rows) if rows else np.zeros((0, 4), dtype=np.int64)
    order = np.lexsort((rows[:, 3], rows[:, 1], rows[:, 2], rows[:, 0]))
    np.savetxt(out, rows[order], fmt="%d", delimiter=",", header="t_us,x,y,on", comments="")
    print(f"naive: {len(rows)} events from {len(frames)} frames, threshold {c}")


if __name__ == "__main__":
    main(sys.argv)
