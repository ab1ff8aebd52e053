"""Stage 2's evaluation written in numpy alone, for the speed and the scores of
`v2ce eval stage2` to be checked against.

The same protocol (docs/stage2.md, src/metrics/stage2.rs): fixed-rate frame intervals from the
first event (boundaries `first + floor(i * 1e6 / fps)`), a 10-node bilinear voxel per interval
normalised to the frame times, chain decoupling on cumulative sums (counts `ceil(V_i - tol)`,
the last node folded with `round`), each sub-interval's events evenly spaced around their mean
(`moment`'s placement, without its count search), and C-METE: per interval, each event's
distance to the nearest re-sampled event of the same pixel and polarity, capped at 3 T / 10,
averaged, then averaged over intervals.

Usage: python tools/stage2_numpy.py EVENTS.csv [--fps 30] [--bins 10] [--predicted OUT.csv]
(EVENTS.csv as `v2ce transcode FILE EVENTS.csv` writes it: t_us,x,y,on). Prints one JSON line:
C-METE, PGER, the events, and the seconds spent (reading the CSV apart). With --predicted
(what `v2ce eval stage2 --write-events` wrote), those events are scored instead of its own: an
independent check of the metric.
"""

import argparse
import json
import time

import numpy as np


def intervals(first, last, fps):
    period = 1e6 / fps
    n = int(np.floor((last - first) / period)) + 1
    bounds = first + np.floor(np.arange(n + 1) * period).astype(np.int64)
    return bounds


def resample(t, key, start, duration, bins):
    """The voxel of one interval's events, decoupled and re-timed: (key, t) of the result."""
    k = bins - 1
    tau = np.clip((t - start) * (k / duration), 0.0, k)
    a = np.minimum(np.floor(tau).astype(np.int64), k - 1)
    frac = tau - a
    cells, cell = np.unique(key, return_inverse=True)
    vox = np.zeros(len(cells) * bins)
    np.add.at(vox, cell * bins + a, 1.0 - frac)
    np.add.at(vox, cell * bins + a + 1, frac)
    cum = np.cumsum(vox.reshape(-1, bins), axis=1)
    tol = 1e-6 + 1e-9 * np.abs(cum)
    through = np.maximum(np.ceil(cum[:, :k] - tol[:, :k]), 0.0)
    through = np.maximum.accumulate(through, axis=1)
    total = np.maximum(through[:, k - 1], np.maximum(np.round(cum[:, k]), 0.0))
    through[:, k - 1] = total
    counts = np.diff(np.concatenate([np.zeros((len(cells), 1)), through], axis=1), axis=1)
    sums = np.clip(through - cum[:, :k], 0.0, counts)
    counts = counts.astype(np.int64).ravel()
    live = counts > 0
    m = counts[live]
    mean = np.clip(sums.ravel()[live] / m, 0.0, 1.0 - 2**-53)
    sub = np.tile(np.arange(k), len(cells))[live]
    owner = np.repeat(np.arange(len(cells)), k)[live]
    width = np.minimum(1.0, np.minimum(2.0 * mean, 2.0 * (1.0 - mean)))
    # The j-th of m events: mean - width / 2 + (j + 1/2) width / m.
    rep = np.repeat(np.arange(len(m)), m)
    j = np.arange(len(rep)) - np.repeat(np.cumsum(m) - m, m)
    pos = mean[rep] - width[rep] / 2 + (j + 0.5) * width[rep] / m[rep]
    pos = sub[rep] + np.clip(pos, 0.0, 1.0 - 2**-53)
    out_t = start + np.clip(np.round(pos * duration / k), 0, duration - 1).astype(np.int64)
    return cells[owner[rep]], out_t


def score(t, key, pt, pkey, cap):
    order = np.lexsort((pt, pkey))
    pkey, pt = pkey[order], pt[order]
    lo = np.searchsorted(pkey, key, "left")
    hi = np.searchsorted(pkey, key, "right")
    # Within each key's run, the first predicted time at or after t.
    # One sorted integer per predicted event: its key, then its offset in the interval.
    start = min(t.min(), pt.min())
    comb = (pkey << 26) + (pt - start)
    q = np.searchsorted(comb, (key << 26) + (t - start), "left")
    best = np.full(len(t), 1e6)
    after = q < hi
    best[after] = pt[q[after]] - t[after]
    before = q - 1 >= lo
    best[before] = np.minimum(best[before], t[before] - pt[q[before] - 1])
    return np.minimum(best, cap).mean()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("events")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--bins", type=int, default=10)
    ap.add_argument("--predicted")
    args = ap.parse_args()
    ev = np.loadtxt(args.events, delimiter=",", skiprows=1, dtype=np.int64)
    given = None
    if args.predicted:
        given = np.loadtxt(args.predicted, delimiter=",", skiprows=1, dtype=np.int64)
        given_key = (given[:, 2] << 17) | (given[:, 1] << 1) | given[:, 3]
    began = time.perf_counter()
    t, x, y, on = ev[:, 0], ev[:, 1], ev[:, 2], ev[:, 3]
    key = (y << 17) | (x << 1) | on
    bounds = intervals(t[0], t[-1], args.fps)
    metes, pgers, produced = [], [], 0
    for a, b in zip(bounds[:-1], bounds[1:]):
        lo, hi = np.searchsorted(t, [a, b])
        if hi <= lo:
            continue
        if given is None:
            pkey, pt = resample(t[lo:hi], key[lo:hi], a, b - a, args.bins)
        else:
            plo, phi = np.searchsorted(given[:, 0], [a, b])
            pkey, pt = given_key[plo:phi], given[plo:phi, 0]
        produced += len(pt)
        metes.append(score(t[lo:hi], key[lo:hi], pt, pkey, 3.0 * (b - a) / 10.0))
        pgers.append(len(pt) / (hi - lo))
    seconds = time.perf_counter() - began
    mete, pger = float(np.mean(metes)), float(np.mean(pgers))
    print(json.dumps({"c_mete_us": mete * max(1.0, pger), "pger": pger, "events_in": len(t),
                      "events_out": produced, "intervals": len(metes), "seconds": seconds}))


if __name__ == "__main__":
    main()
