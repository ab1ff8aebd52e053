"""v2ce: video to DVS events (the V2CE method) on v2ce's Rust core.

Events are one numpy structured array with fields ``t`` (int64 microseconds), ``x``, ``y``
(uint16) and ``p`` (int8: 1 = ON, 0 = OFF), the layout tonic's transforms take as it is (``p``
is signed because tonic's ``ToVoxelGrid`` rewrites OFF as -1 in place; every function here
reads ``p > 0`` as ON)::

    import v2ce, tonic
    events = v2ce.convert("clip.mp4")                          # or frames: (N, H, W) + times_us
    frames = tonic.transforms.ToFrame(sensor_size=(*v2ce.size_of(events), 2), n_time_bins=10)(events)

Every function releases the GIL while the core works, raises ``ValueError`` (bad input),
``OSError`` (files) or ``RuntimeError`` (a failed run) with the command line's one-line message,
and gives the same events as the ``v2ce`` command for the same frames, settings and seed.
"""

from __future__ import annotations

import json
import os
from typing import Iterator, Optional, Tuple, Union

import numpy as np

from . import _v2ce

__all__ = [
    "EVENT_DTYPE",
    "Reader",
    "Simulator",
    "convert",
    "eval_stage1",
    "eval_stage2",
    "open",
    "read",
    "sample",
    "size_of",
    "voxelize",
    "write",
]

__version__ = _v2ce.version()

#: The events' dtype: ``t`` int64 us, ``x`` and ``y`` uint16, ``p`` int8 (1 = ON, 0 = OFF);
#: 16 bytes a record, aligned.
EVENT_DTYPE = np.dtype(
    {
        "names": ["t", "x", "y", "p"],
        "formats": ["<i8", "<u2", "<u2", "i1"],
        "offsets": [0, 8, 10, 12],
        "itemsize": _v2ce.RECORD_BYTES,
    }
)

PathLike = Union[str, "os.PathLike[str]"]
Size = Union[Tuple[int, int], str]

def _events(records: np.ndarray, size: Optional[Tuple[int, int]] = None) -> np.ndarray:
    """The core's packed records as the structured array (a view, no copy); the sensor size
    rides in the dtype's metadata (kept by slices and views)."""
    if size is None:
        return records.view(EVENT_DTYPE)
    dtype = np.dtype(EVENT_DTYPE, metadata={"sensor_size": (int(size[0]), int(size[1]))})
    return records.view(dtype)


def size_of(events: np.ndarray) -> Tuple[int, int]:
    """The sensor size (width, height) of an array this package returned (kept in its
    dtype's metadata), else one more than the largest column and row."""
    meta = events.dtype.metadata or {}
    if "sensor_size" in meta:
        w, h = meta["sensor_size"]
        return (int(w), int(h))
    if len(events) == 0:
        return (0, 0)
    return (int(events["x"].max()) + 1, int(events["y"].max()) + 1)


def _size(size: Optional[Size]) -> Optional[Tuple[int, int]]:
    if size is None:
        return None
    if isinstance(size, str):
        w, sep, h = size.lower().partition("x")
        if not sep:
            raise ValueError(f"size '{size}': expected WIDTHxHEIGHT, e.g. 346x260")
        return (int(w), int(h))
    w, h = size
    return (int(w), int(h))


def _onnxruntime_library() -> Optional[str]:
    """The ONNX Runtime library of this interpreter's ``onnxruntime`` package, if installed
    (found without importing it), for the learned tier; the core also looks in
    ``ORT_DYLIB_PATH``, the current folder's venv and the system's folders."""
    import importlib.util

    spec = importlib.util.find_spec("onnxruntime")
    if spec is None or not spec.submodule_search_locations:
        return None
    for folder in spec.submodule_search_locations:
        capi = os.path.join(folder, "capi")
        if os.path.isdir(capi):
            libs = sorted(f for f in os.listdir(capi) if f.startswith("libonnxruntime.so"))
            if libs:
                return os.path.join(capi, libs[-1])
    return None


def _settings(tier: str, preset: Optional[str], seed: int, mode: Optional[str],
              sampler: Optional[str], model: Optional[PathLike], params: dict) -> dict:
    """The keyword arguments as the configuration's tables (config/v2ce.toml documents every
    key): ``preset``, ``seed``, ``mode`` (stage1.output), ``sampler``; ``params`` go to the
    tier's own table (``[stage1.learned]`` for the learned tier, else ``[stage1.physics]``)."""
    if model is not None and tier == "physics":
        tier = "learned"
    stage1: dict = {"tier": tier, "seed": int(seed)}
    if preset is not None:
        stage1["preset"] = preset
    if mode is not None:
        stage1["output"] = mode
    learned: dict = {}
    physics: dict = {}
    if model is not None:
        learned["model"] = os.fspath(model)
    (learned if tier == "learned" else physics).update(params)
    if tier != "physics" and "ort_library" not in learned and not os.environ.get("ORT_DYLIB_PATH"):
        found = _onnxruntime_library()
        if found is not None:
            learned["ort_library"] = found
    if learned:
        stage1["learned"] = learned
    if physics:
        stage1["physics"] = physics
    stage2: dict = {"seed": int(seed)}
    if sampler is not None:
        stage2["sampler"] = sampler
    return {"stage1": stage1, "stage2": stage2}


def convert(
    source: Union[PathLike, np.ndarray],
    *,
    times_us: Optional[np.ndarray] = None,
    fps: Optional[float] = None,
    size: Optional[Size] = None,
    tier: str = "physics",
    preset: Optional[str] = "davis346",
    seed: int = 0,
    mode: Optional[str] = None,
    sampler: Optional[str] = None,
    model: Optional[PathLike] = None,
    color: str = "auto",
    linear: bool = False,
    max_frames: Optional[int] = None,
    config: Optional[PathLike] = None,
    **params,
) -> np.ndarray:
    """Frames to events, as ``v2ce convert`` does.

    ``source`` is a path (a video through ffmpeg, an image folder, a frame list, a ``.y4m``, an
    ``.aedat4`` with APS frames, or ``"fixture"``, the bundled clip) or a numpy array of gray
    frames ``(N, H, W)``: uint8 (sRGB-encoded, as video; ``linear=True`` for raw 8-bit values),
    uint16 (linear 0..65535) or float32 (linear 0..1), at ``times_us`` (int64, increasing),
    read in place when C-contiguous. ``fps`` times an image folder without a times file;
    ``size`` (``(W, H)`` or ``"WxH"``) resamples; ``tier`` is ``"physics"``, ``"learned"``
    (``model=`` an ONNX file, else the built-in one) or ``"auto"``; ``mode`` ``"events"`` or
    ``"voxels"`` (re-timed by ``sampler``); ``config`` a TOML file under the arguments; any
    other keyword is a key of the tier's table (e.g. ``motion="linear"``, ``threshold_on=0.3``).
    Returns the events (``EVENT_DTYPE``), sorted by time; ``size_of`` gives the sensor size.
    """
    settings = _settings(tier, preset, seed, mode, sampler, model, params)
    cfg = None if config is None else os.fspath(config)
    limit = None if max_frames is None or max_frames <= 0 else int(max_frames)
    if isinstance(source, np.ndarray):
        if times_us is None:
            raise ValueError("frames given as an array need times_us (one time per frame, us)")
        frames = source if source.flags.c_contiguous else np.ascontiguousarray(source)
        times = _checked("times_us", times_us, np.int64, round_floats=True)
        records, out_size = _v2ce.convert_frames(
            frames, times, settings, cfg, _size(size), bool(linear), limit
        )
    else:
        if times_us is not None:
            raise ValueError("times_us is for frames given as an array; a file has its own")
        records, out_size = _v2ce.convert_path(
            os.fspath(source), settings, cfg, _size(size), fps, color, limit
        )
    return _events(records, out_size)


class Simulator:
    """Stage 1 and Stage 2 frame by frame, stateful, in the caller's thread (for a DataLoader
    or a live loop): ``push(frame, t_us)`` returns the events of the interval the frame
    closes; ``finish()`` what is held at the end. The pushes' events together equal
    ``convert`` on the same frames and seed. ``linear`` says how uint8 frames are encoded
    (and tells Stage 1 the frames are linear: set it for uint16 and float32 frames)."""

    def __init__(
        self,
        width: int,
        height: int,
        *,
        tier: str = "physics",
        preset: Optional[str] = "davis346",
        seed: int = 0,
        mode: Optional[str] = None,
        sampler: Optional[str] = None,
        model: Optional[PathLike] = None,
        linear: bool = False,
        config: Optional[PathLike] = None,
        **params,
    ) -> None:
        settings = _settings(tier, preset, seed, mode, sampler, model, params)
        cfg = None if config is None else os.fspath(config)
        self._sim = _v2ce.Simulator(int(width), int(height), settings, cfg, bool(linear))

    @property
    def size(self) -> Tuple[int, int]:
        """(width, height)."""
        return self._sim.size

    def push(self, frame: np.ndarray, t_us: int) -> np.ndarray:
        """The events of the interval from the previous frame to ``frame`` (``(H, W)``)."""
        if np.ndim(t_us) != 0:
            raise ValueError(f"t_us: one time, not an array of shape {np.shape(t_us)}")
        t = int(_checked("t_us", [t_us], np.int64, round_floats=True)[0])
        return _events(self._sim.push(np.asarray(frame), t), self._sim.size)

    def finish(self) -> np.ndarray:
        """What Stage 1 still holds; no frame may follow."""
        return _events(self._sim.finish(), self._sim.size)


def read(path: PathLike) -> np.ndarray:
    """Every event of a file (``.aedat4``, ``.raw`` EVT 2.0/3.0, ``.csv``, ``.npz``,
    ``.h5``/``.hdf5``, IJRR ``events.txt``), sorted by time; ``size_of`` gives its sensor size."""
    records, size = _v2ce.read(os.fspath(path))
    return _events(records, size)


def _checked(name: str, values, dtype, round_floats: bool = False) -> np.ndarray:
    """``values`` as a contiguous ``dtype`` array, refusing what a cast would change silently:
    NaN and infinities, values outside the type's range, and (unless ``round_floats``, which
    rounds them to the nearest integer) floats that are not whole numbers."""
    a = np.asarray(values)
    if a.dtype.kind == "f":
        if a.size and not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: NaN or infinite values")
        if round_floats:
            a = np.rint(a)
        elif a.size and not np.all(a == np.floor(a)):
            raise ValueError(f"{name}: values that are not whole numbers")
    elif a.dtype.kind not in "iub":
        raise ValueError(f"{name}: {a.dtype} values, expected numbers")
    info = np.iinfo(dtype)
    if a.size:
        lo, hi = a.min(), a.max()
        if a.dtype.kind == "f":
            # As floats: the type's top + 1 is a power of two, exact as a float.
            outside = float(lo) < float(info.min) or float(hi) >= float(info.max) + 1.0
        else:
            # As Python integers: exact for every integer type, uint64 included.
            outside = int(lo) < info.min or int(hi) > info.max
        if outside:
            raise ValueError(
                f"{name}: values from {lo} to {hi}, outside {np.dtype(dtype).name}'s {info.min}..{info.max}"
            )
    return np.ascontiguousarray(a, dtype=dtype)


def _columns(events: np.ndarray):
    names = events.dtype.names or ()
    missing = [f for f in ("t", "x", "y", "p") if f not in names]
    if missing:
        raise ValueError(
            f"events need fields t, x, y, p (missing {', '.join(missing)}); "
            "the toolbox's npz names map as timestamp->t, polarity->p"
        )
    p = np.asarray(events["p"])
    return (
        _checked("t", events["t"], np.int64, round_floats=True),
        _checked("x", events["x"], np.uint16),
        _checked("y", events["y"], np.uint16),
        np.ascontiguousarray(p > 0, dtype=np.uint8),
    )


def write(
    path: PathLike,
    events: np.ndarray,
    size: Optional[Size] = None,
    *,
    evt: int = 2,
    compression: str = "lz4",
) -> None:
    """Writes events (any structured array with fields t, x, y, p; p > 0 is ON) in the format
    the extension names, as ``v2ce transcode`` would: under a partial name until complete.
    ``size`` defaults to ``size_of(events)``."""
    w, h = _size(size) or size_of(events)
    t, x, y, p = _columns(events)
    _v2ce.write(os.fspath(path), t, x, y, p, int(w), int(h), int(evt), compression)


def _times(frame_times_us) -> np.ndarray:
    return _checked("frame_times_us", frame_times_us, np.int64, round_floats=True)


def voxelize(
    events: np.ndarray, frame_times_us, bins: int = 10, size: Optional[Size] = None
) -> np.ndarray:
    """Each frame interval's events as a voxel grid: float32 ``(intervals, 2 * bins, H, W)`` in
    V2CE's layout (channel = polarity * bins + node, ON first), as ``convert --write-voxels``
    writes Stage 1's. ``size`` defaults to ``size_of(events)``."""
    w, h = _size(size) or size_of(events)
    return _v2ce.voxelize(_columns(events), _times(frame_times_us), int(w), int(h), int(bins))


def sample(voxels: np.ndarray, frame_times_us, sampler: str = "spatial", seed: int = 0) -> np.ndarray:
    """Events re-timed from voxels ``(intervals, 2 * bins, H, W)`` (``len(frame_times_us)`` is
    one more than the intervals) by a Stage 2 sampler: ``spatial`` (the default), ``moment``,
    ``ldati``, ``ldati-random``, ``even`` or ``random``. Every cell's count is kept."""
    v = np.ascontiguousarray(voxels, dtype=np.float32)
    if v.ndim != 4:
        raise ValueError(f"voxels: {v.ndim} dimensions; expected (intervals, 2 * bins, H, W)")
    return _events(_v2ce.sample(v, _times(frame_times_us), sampler, int(seed)),
                   (v.shape[3], v.shape[2]))


def eval_stage1(real: np.ndarray, sim: np.ndarray, frame_times_us,
                size: Optional[Size] = None) -> dict:
    """``v2ce eval stage1``'s scores of ``sim`` against ``real`` on the frame intervals: TPF1,
    TF1, RF1, accuracies, PMSE-2/4, event counts and ratio, C-METE, METE, PGER."""
    w, h = _size(size) or size_of(real)
    return json.loads(_v2ce.eval_stage1(_columns(real), _columns(sim), _times(frame_times_us),
                                        int(w), int(h)))


def eval_stage2(events: np.ndarray, frame_times_us, sampler: str = "spatial", bins: int = 10,
                seed: int = 0, size: Optional[Size] = None) -> dict:
    """``v2ce eval stage2``'s scores: the events voxelized per frame interval, re-timed by
    ``sampler`` and compared with themselves (C-METE, METE, PGER, timings)."""
    w, h = _size(size) or size_of(events)
    return json.loads(_v2ce.eval_stage2(_columns(events), _times(frame_times_us), int(w), int(h),
                                        sampler, int(bins), int(seed)))


class Reader:
    """An event file read a chunk at a time (``chunks(n)``), for files larger than memory."""

    def __init__(self, path: PathLike) -> None:
        self._reader = _v2ce.Reader(os.fspath(path))

    @property
    def size(self) -> Optional[Tuple[int, int]]:
        """The sensor size the file states, if any."""
        return self._reader.size

    def chunks(self, n: int = 1 << 20) -> Iterator[np.ndarray]:
        """Arrays of about ``n`` events each, in the file's order, until the end."""
        while True:
            chunk = self._reader.read(int(n))
            if len(chunk) == 0:
                return
            yield _events(chunk, self._reader.size)


def open(path: PathLike) -> Reader:  # noqa: A001 (the API's name, as in the issue)
    """A ``Reader`` on ``path``."""
    return Reader(path)
