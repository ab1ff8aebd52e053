"""Toolbox preprocessing, sequence planning and merge (spec 1.2 and 1.3).

No resizing here: the parity fixtures test the network at the input's own size.
"""

from __future__ import annotations

from typing import List, Sequence

import numpy as np

MEAN = 0.153
STD = 0.165
L = 16  # frame pairs per sequence


def normalize(gray: np.ndarray) -> np.ndarray:
    """uint8 gray -> float32 (gray/255 - 0.153)/0.165, in float32 like the toolbox."""
    x = gray.astype(np.float32) / np.float32(255.0)
    return (x - np.float32(MEAN)) / np.float32(STD)


def make_pairs(frames: np.ndarray) -> np.ndarray:
    """(N, H, W) normalized frames -> (N-1, 2, H, W) pairs (earlier, later)."""
    return np.stack([frames[:-1], frames[1:]], axis=1)


def plan_starts(n_frames: int) -> List[int]:
    """Start frames of the 17-frame sequences for N frames (spec 1.3).

    S = ceil((N-1)/16) sequences at 16k; if (N-1) % 16 != 0 the last start moves back
    to N-17 so the last sequence ends on the final frame. Requires N >= 17.
    """
    if n_frames < L + 1:
        raise ValueError("need at least 17 frames")
    intervals = n_frames - 1
    s = -(-intervals // L)
    starts = [L * k for k in range(s)]
    if intervals % L:
        starts[-1] = n_frames - (L + 1)
    return starts


def sequences(pairs: np.ndarray, starts: Sequence[int]) -> np.ndarray:
    """(N-1, 2, H, W) pairs -> (S, 16, 2, H, W) model input, one sequence per start."""
    return np.stack([pairs[s:s + L] for s in starts])


def merge(outputs: np.ndarray, n_frames: int) -> np.ndarray:
    """(S, 16, 20, H, W) predictions -> (N-1, 20, H, W) (spec 1.3 merge).

    All 16 intervals of every sequence but the last; from the last only its final
    m = (N-1) % 16 intervals (all 16 when m == 0).
    """
    m = (n_frames - 1) % L
    parts = list(outputs[:-1])
    parts.append(outputs[-1][L - m:] if m else outputs[-1])
    merged = np.concatenate(parts, axis=0)
    assert merged.shape[0] == n_frames - 1
    return merged
