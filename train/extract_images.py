"""Writes the natural images that ship inside scikit-image (its data module; nothing is
downloaded) as 8-bit grayscale PNGs, for `v2ce dataset synthetic --images DIR`.

    python extract_images.py DIR
"""

import os
import sys

import numpy as np
from PIL import Image
from skimage import color, data

# Images bundled in the scikit-image wheel (no network fetch).
NAMES = [
    "astronaut", "brick", "camera", "cat", "clock", "coffee", "coins", "grass", "gravel",
    "horse", "microaneurysms", "moon", "page", "rocket", "text", "chelsea", "hubble_deep_field",
    "immunohistochemistry", "retina", "logo", "colorwheel",
]


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    written = 0
    for name in NAMES:
        fetch = getattr(data, name, None)
        if fetch is None:
            continue
        try:
            img = np.asarray(fetch())
        except Exception as e:  # not bundled in this version: skip, say so
            print(f"skipped {name}: {type(e).__name__}", file=sys.stderr)
            continue
        if img.ndim == 3:
            img = color.rgb2gray(img[..., :3]) * 255.0
        elif img.dtype == bool:
            img = img.astype(np.float32) * 255.0
        img = np.clip(img, 0, 255).astype(np.uint8)
        if min(img.shape[:2]) < 32:
            continue
        Image.fromarray(img).save(os.path.join(out, f"{name}.png"))
        written += 1
    print(f"{written} images in {out}")


if __name__ == "__main__":
    main()
