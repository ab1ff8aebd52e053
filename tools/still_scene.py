"""Writes the still-camera clip of the README's crop measurement: scikit-image's "brick"
texture at 640x480 as a still background and its "camera" image at 48x48 moving 4 px per
frame, 33 gray frames at 30 fps, as a Y4M (nothing is downloaded; needs numpy, pillow and
scikit-image, e.g. train/.venv).

    python tools/still_scene.py still640.y4m
    v2ce convert still640.y4m --stage1 learned --threads 2 -o ev.csv            # crops
    v2ce convert still640.y4m --stage1 learned --threads 2 --no-roi -o whole.csv
"""

import sys

import numpy as np
from PIL import Image
from skimage import data


def gray(img):
    return Image.fromarray(np.asarray(img, dtype=np.uint8)).convert("L")


def main():
    out = sys.argv[1]
    background = np.asarray(gray(data.brick()).resize((640, 480)), dtype=np.uint8)
    thing = np.asarray(gray(data.camera()).resize((48, 48)), dtype=np.uint8)
    with open(out, "wb") as f:
        f.write(b"YUV4MPEG2 W640 H480 F30:1 Ip A1:1 Cmono\n")
        for i in range(33):
            frame = background.copy()
            x, y = 100 + 4 * i, 200
            frame[y:y + 48, x:x + 48] = thing
            f.write(b"FRAME\n")
            f.write(frame.tobytes())


if __name__ == "__main__":
    main()
