"""Minimal PNG reader/writer for 8-bit grayscale images (standard library + numpy).

Enough for the DAVIS346 APS frames (colour type 0, bit depth 8, no interlace) and for
writing the cropped fixture frames, without depending on Pillow or OpenCV.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    if pa <= pb and pa <= pc:
        return a
    return b if pb <= pc else c


def _unfilter(raw: bytes, height: int, width: int) -> np.ndarray:
    """Undo the per-row PNG filters (bytes per pixel = 1)."""
    out = np.zeros((height, width), dtype=np.uint8)
    stride = width + 1
    prev = np.zeros(width, dtype=np.int64)
    for y in range(height):
        ftype = raw[y * stride]
        line = np.frombuffer(raw, np.uint8, width, y * stride + 1).astype(np.int64)
        if ftype == 0:
            cur = line
        elif ftype == 1:   # Sub
            cur = np.cumsum(line) & 0xFF
        elif ftype == 2:   # Up
            cur = (line + prev) & 0xFF
        elif ftype in (3, 4):  # Average, Paeth: sequential in x
            cur = np.zeros(width, dtype=np.int64)
            left = 0
            for x in range(width):
                up = int(prev[x])
                if ftype == 3:
                    pred = (left + up) >> 1
                else:
                    pred = _paeth(left, up, int(prev[x - 1]) if x else 0)
                left = (int(line[x]) + pred) & 0xFF
                cur[x] = left
        else:
            raise ValueError(f"bad PNG filter type {ftype}")
        out[y] = cur
        prev = cur
    return out


def read_gray8(path: str) -> np.ndarray:
    """Read an 8-bit grayscale, non-interlaced PNG into a (H, W) uint8 array."""
    with open(path, "rb") as f:
        data = f.read()
    if not data.startswith(SIGNATURE):
        raise ValueError(f"{path}: not a PNG")
    pos, idat, hdr = 8, [], None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        ctype = data[pos + 4:pos + 8]
        body = data[pos + 8:pos + 8 + length]
        crc = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])[0]
        if zlib.crc32(ctype + body) & 0xFFFFFFFF != crc:
            raise ValueError(f"{path}: CRC mismatch in {ctype!r}")
        if ctype == b"IHDR":
            hdr = struct.unpack(">IIBBBBB", body)
        elif ctype == b"IDAT":
            idat.append(body)
        elif ctype == b"IEND":
            break
        pos += 12 + length
    if hdr is None:
        raise ValueError(f"{path}: no IHDR")
    width, height, depth, color, _comp, _filt, interlace = hdr
    if (depth, color, interlace) != (8, 0, 0):
        raise ValueError(f"{path}: only 8-bit gray non-interlaced PNGs are supported")
    raw = zlib.decompress(b"".join(idat))
    if len(raw) != height * (width + 1):
        raise ValueError(f"{path}: bad image data size")
    return _unfilter(raw, height, width)


def _chunk(ctype: bytes, body: bytes) -> bytes:
    return (struct.pack(">I", len(body)) + ctype + body
            + struct.pack(">I", zlib.crc32(ctype + body) & 0xFFFFFFFF))


def write_gray8(path: str, img: np.ndarray) -> None:
    """Write a (H, W) uint8 array as an 8-bit grayscale PNG (filter 0, zlib level 9)."""
    img = np.ascontiguousarray(img, dtype=np.uint8)
    height, width = img.shape
    raw = b"".join(b"\x00" + img[y].tobytes() for y in range(height))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    with open(path, "wb") as f:
        f.write(SIGNATURE + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw, 9))
                + _chunk(b"IEND", b""))
