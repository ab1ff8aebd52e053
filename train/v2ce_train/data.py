"""Datasets written by ``v2ce dataset`` (a folder of ``seq_NNNNN.npz`` and ``dataset.json``),
as network inputs and targets, with the toolbox's preprocessing (V2CE_SPEC.md section 1.1):
frames / 255, normalised by (x - 0.153) / 0.165, paired (earlier, later)."""

import json
import os

import numpy as np
import torch

MEAN, STD = 0.153, 0.165


class Sequences:
    """Every sequence of one or more dataset folders, read from disk when drawn (a dataset of
    hundreds of sequences does not fit in memory)."""

    def __init__(self, folders):
        self.paths = []
        for folder in folders:
            with open(os.path.join(folder, "dataset.json")) as f:
                manifest = json.load(f)
            self.paths += [os.path.join(folder, s["file"]) for s in manifest["sequences"]]
        if not self.paths:
            raise ValueError(f"no sequences in {folders}")

    def load(self, k):
        z = np.load(self.paths[k])
        return z["frames"], z["voxels"]

    def __len__(self):
        return len(self.paths)

    @staticmethod
    def inputs(frames):
        """uint8 (L+1, H, W) -> float32 (L, 2, H, W), normalised pairs."""
        x = (frames.astype(np.float32) / 255.0 - MEAN) / STD
        return np.stack([x[:-1], x[1:]], axis=1)

    def sample(self, rng, batch, crop=None, window=None):
        """A random batch: inputs (B, L, 2, h, w) and voxels (B, L, 20, h, w), with a random
        crop of size `crop` (h, w) and a random window of `window` intervals."""
        xs, ys = [], []
        for _ in range(batch):
            f, v = self.load(int(rng.integers(len(self.paths))))
            pairs, h, w = v.shape[0], v.shape[2], v.shape[3]
            l = pairs if window is None else min(window, pairs)
            t0 = int(rng.integers(pairs - l + 1))
            ch, cw = (h, w) if crop is None else (min(crop[0], h), min(crop[1], w))
            y0, x0 = int(rng.integers(h - ch + 1)), int(rng.integers(w - cw + 1))
            xs.append(self.inputs(f[t0 : t0 + l + 1, y0 : y0 + ch, x0 : x0 + cw]))
            ys.append(v[t0 : t0 + l, :, y0 : y0 + ch, x0 : x0 + cw])
        return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys))

    def whole(self, k):
        """Sequence `k` whole: inputs (1, L, 2, H, W) and voxels (1, L, 20, H, W)."""
        f, v = self.load(k)
        return torch.from_numpy(self.inputs(f)[None]), torch.from_numpy(np.ascontiguousarray(v[None]))
