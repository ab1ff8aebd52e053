"""The Python package against the command line, tonic, and bad input.

Run by .ci/run after `pip install ./python` into the project's venv: `pytest python/tests`. The
CLI is `V2CE_BIN`, else the repository's `target/release/v2ce` (built by the Rust tests).
"""

import os
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pytest

import v2ce

ROOT = Path(__file__).resolve().parents[2]
CLI = Path(os.environ.get("V2CE_BIN", ROOT / "target" / "release" / "v2ce"))


def cli(*args, cwd=None):
    if not CLI.exists():
        pytest.fail(f"no v2ce binary at {CLI} (cargo build --release, or set V2CE_BIN)")
    # From the repository, where the CLI finds the venv's ONNX Runtime as a user's run would.
    out = subprocess.run([str(CLI), *map(str, args)], cwd=cwd or ROOT, capture_output=True,
                         text=True)
    assert out.returncode == 0, out.stderr
    return out


def same(a, b):
    assert len(a) == len(b), (len(a), len(b))
    for f in ("t", "x", "y"):
        assert np.array_equal(a[f].astype(np.int64), b[f].astype(np.int64)), f
    assert np.array_equal(a["p"] > 0, b["p"] > 0), "p"


def moving_bar(n=12, h=48, w=64):
    """Gray uint8 frames of a bright bar moving right over a dark background."""
    frames = np.full((n, h, w), 30, np.uint8)
    for k in range(n):
        x0 = 4 + 3 * k
        frames[k, :, x0 : x0 + 8] = 220
    return frames


def write_png(path, gray):
    """A minimal 8-bit grayscale PNG (no imaging library needed)."""
    h, w = gray.shape
    raw = b"".join(b"\x00" + gray[r].tobytes() for r in range(h))

    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    png = b"\x89PNG\r\n\x1a\n"
    png += chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw))
    png += chunk(b"IEND", b"")
    path.write_bytes(png)


def test_convert_of_a_path_is_the_cli_event_for_event(tmp_path):
    cli("convert", "fixture", "--max-frames", "12", "--seed", "5", "-o", tmp_path / "cli.csv")
    want = v2ce.read(tmp_path / "cli.csv")
    got = v2ce.convert("fixture", max_frames=12, seed=5)
    assert len(got) > 10_000
    same(got, want)
    assert v2ce.size_of(got) == (640, 480)
    # Another seed, other events (the seed reaches mismatch and noise).
    other = v2ce.convert("fixture", max_frames=12, seed=6)
    assert len(other) != len(got) or not np.array_equal(other["t"], got["t"])


def shared_data():
    """../shared/data (V2CE_DATA to override), or a skip that says why."""
    d = Path(os.environ.get("V2CE_DATA", ROOT.parent / "shared" / "data"))
    if not d.is_dir():
        pytest.skip(f"SKIPPED: no recordings at {d} (see docs/testing.md)")
    return d


def test_the_davis346_aps_frames_give_the_cli_events(tmp_path):
    clip = shared_data() / "davis346" / "davis346.aedat4"
    cli("convert", clip, "--seed", "2", "--max-frames", "40", "-o", tmp_path / "cli.aedat4")
    want = v2ce.read(tmp_path / "cli.aedat4")
    got = v2ce.convert(clip, seed=2, max_frames=40)
    assert len(got) > 1000
    same(got, want)
    assert v2ce.size_of(got) == (346, 260)


def test_numpy_frames_are_the_cli_on_the_same_images(tmp_path):
    frames = moving_bar()
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, f in enumerate(frames):
        write_png(folder / f"{k:03d}.png", f)
    cli("convert", folder, "--fps", "100", "--color", "srgb", "--seed", "3",
        "-o", tmp_path / "cli.aedat4")
    want = v2ce.read(tmp_path / "cli.aedat4")
    times = np.arange(len(frames), dtype=np.int64) * 10_000
    got = v2ce.convert(frames, times_us=times, seed=3)
    assert len(got) > 100
    same(got, want)
    # A non-contiguous view is copied once and gives the same.
    wide = np.ascontiguousarray(np.repeat(frames, 2, axis=2))[:, :, ::2]
    same(v2ce.convert(wide, times_us=times, seed=3), got)


def test_the_learned_tier_is_the_cli_where_onnx_runtime_is(tmp_path):
    import importlib.util

    if importlib.util.find_spec("onnxruntime") is None:
        pytest.skip("SKIPPED: no onnxruntime in this interpreter (pip install onnxruntime)")
    frames = moving_bar(n=10)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k, f in enumerate(frames):
        write_png(folder / f"{k:03d}.png", f)
    cli("convert", folder, "--fps", "100", "--color", "srgb", "--stage1", "learned",
        "-o", tmp_path / "cli.aedat4")
    want = v2ce.read(tmp_path / "cli.aedat4")
    got = v2ce.convert(frames, times_us=np.arange(10, dtype=np.int64) * 10_000, tier="learned")
    assert len(got) > 100
    same(got, want)


def test_the_streaming_simulator_equals_convert():
    frames = moving_bar(n=15)
    times = np.arange(len(frames), dtype=np.int64) * 33_333
    whole = v2ce.convert(frames, times_us=times, seed=9, motion="linear")
    sim = v2ce.Simulator(64, 48, seed=9, motion="linear")
    parts = [sim.push(f, t) for f, t in zip(frames, times)] + [sim.finish()]
    assert len(parts[0]) == 0  # the first frame only sets the pixels
    same(np.concatenate(parts), whole)
    with pytest.raises(ValueError, match="after finish"):
        sim.push(frames[0], 10**9)


def test_every_format_round_trips_and_reads_like_the_cli(tmp_path):
    events = v2ce.convert(moving_bar(), times_us=np.arange(12, dtype=np.int64) * 10_000)
    size = v2ce.size_of(events)
    assert size == (64, 48)
    for name, kwargs in [
        ("e.aedat4", {}),
        ("e2.raw", {"evt": 2}),
        ("e3.raw", {"evt": 3}),
        ("e.csv", {}),
        ("e.npz", {}),
        ("e.h5", {}),
    ]:
        path = tmp_path / name
        v2ce.write(path, events, size, **kwargs)
        back = v2ce.read(path)
        same(back, events)
        # In chunks, as for files larger than memory.
        reader = v2ce.open(path)
        chunks = list(reader.chunks(100))
        assert len(chunks) > 1
        same(np.concatenate(chunks), events)
        # The CLI reads what we write.
        cli("transcode", path, tmp_path / f"{name}.csv")
        same(v2ce.read(tmp_path / f"{name}.csv"), events)
    assert not list(tmp_path.glob("*.partial.*"))


def test_tonic_transforms_take_the_arrays_unchanged():
    tonic = pytest.importorskip("tonic", reason="tonic is not installed (pip install tonic)")
    events = v2ce.convert("fixture", max_frames=6)
    w, h = v2ce.size_of(events)
    # The same values in tonic's own layout (its events_struct), for reference; and with an
    # integer p, as tonic's datasets have it (its ToVoxelGrid rewrites OFF as -1 in place, which a
    # bool p turns into ON).
    own = tonic.io.make_structured_array(
        events["x"], events["y"], events["t"], (events["p"] > 0).astype(int)
    )
    ints = tonic.io.make_structured_array(
        events["x"], events["y"], events["t"], (events["p"] > 0).astype(int),
        dtype=np.dtype([("x", int), ("y", int), ("t", int), ("p", int)]),
    )
    sensor = (w, h, 2)
    frames = tonic.transforms.ToFrame(sensor_size=sensor, n_time_bins=4)(events)
    assert frames.shape == (4, 2, h, w)
    assert frames.sum() >= 0.99 * len(events)
    assert np.array_equal(frames, tonic.transforms.ToFrame(sensor_size=sensor, n_time_bins=4)(own))
    voxels = tonic.transforms.ToVoxelGrid(sensor_size=sensor, n_time_bins=5)(events.copy())
    assert voxels.shape == (5, 1, h, w)
    assert np.isfinite(voxels).all() and np.abs(voxels).sum() > 0
    assert np.array_equal(
        voxels, tonic.transforms.ToVoxelGrid(sensor_size=sensor, n_time_bins=5)(ints)
    )
    denoised = tonic.transforms.Denoise(filter_time=10_000)(events)
    assert 0 < len(denoised) <= len(events)
    assert len(denoised) == len(tonic.transforms.Denoise(filter_time=10_000)(own))


def test_bad_input_raises_the_cli_message():
    frames = moving_bar(n=3)
    times = np.array([0, 10_000, 20_000], np.int64)
    with pytest.raises(ValueError, match="dtype"):
        v2ce.convert(frames.astype(np.int32), times_us=times)
    with pytest.raises(ValueError, match="dimensions"):
        v2ce.convert(frames[0], times_us=times[:1])
    with pytest.raises(ValueError, match="increase"):
        v2ce.convert(frames, times_us=np.array([0, 20_000, 10_000], np.int64))
    with pytest.raises(ValueError, match="times_us has 2 values"):
        v2ce.convert(frames, times_us=times[:2])
    with pytest.raises(ValueError, match="times_us"):
        v2ce.convert(frames)
    nan = frames.astype(np.float32) / 255
    nan[1, 5, 5] = np.nan
    with pytest.raises(ValueError, match="(?i)nan"):
        v2ce.convert(nan, times_us=times)
    with pytest.raises(OSError, match="no-such-video"):
        v2ce.convert("no-such-video.mp4")
    with pytest.raises(ValueError, match="hubble"):
        v2ce.convert(frames, times_us=times, preset="hubble")
    with pytest.raises(ValueError, match="not_a_key"):
        v2ce.convert(frames, times_us=times, not_a_key=1)
    with pytest.raises(ValueError):
        v2ce.convert(frames, times_us=times, max_subframes=-3)
    sim = v2ce.Simulator(64, 48)
    sim.push(frames[0], 0)
    with pytest.raises(ValueError, match="does not come after"):
        sim.push(frames[1], 0)
    with pytest.raises(ValueError, match="shape"):
        sim.push(frames[1][:10], 50_000)
    with pytest.raises(ValueError):
        v2ce.Simulator(0, 48)
    with pytest.raises(ValueError, match="fields"):
        v2ce.write("x.csv", np.zeros(3, [("timestamp", "i8"), ("x", "u2")]), (4, 4))
    with pytest.raises(OSError):
        v2ce.read("/nonexistent/events.aedat4")


def test_float_and_16_bit_frames_are_linear_light():
    frames = moving_bar(n=6)
    times = np.arange(6, dtype=np.int64) * 10_000
    as_u16 = v2ce.convert((frames.astype(np.uint16) * 257), times_us=times)
    as_f32 = v2ce.convert(frames.astype(np.float32) / 255, times_us=times)
    as_u8 = v2ce.convert(frames, times_us=times, linear=True)
    same(as_u16, as_u8)
    same(as_f32, as_u8)


def test_ctrl_c_interrupts_a_long_convert():
    # Python installs its Ctrl-C handler only where SIGINT is not ignored when it starts, and a
    # shell ignores SIGINT in the jobs it starts in the background (a CI runner under nohup):
    # the child takes the handler an interactive Python has, whatever it inherited.
    code = (
        "import signal, sys, v2ce\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "print('started', flush=True)\n"
        "try:\n"
        "    v2ce.convert('fixture', size=(1280, 720))\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted', flush=True)\n"
        "    sys.exit(3)\n"
    )
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "started"
    time.sleep(1.5)
    sent = time.monotonic()
    child.send_signal(signal.SIGINT)
    out, _ = child.communicate(timeout=30)
    assert child.returncode == 3, out
    assert "interrupted" in out
    assert time.monotonic() - sent < 10


def test_voxels_round_trip_through_every_sampler_with_exact_counts():
    frames = moving_bar(n=8)
    times = np.arange(8, dtype=np.int64) * 10_000
    events = v2ce.convert(frames, times_us=times)
    vox = v2ce.voxelize(events, times, bins=10)
    assert vox.shape == (7, 20, 48, 64) and vox.dtype == np.float32
    assert abs(vox.sum() - len(events)) < 1e-3 * len(events)
    for sampler in ["spatial", "moment", "ldati", "ldati-random", "even", "random"]:
        back = v2ce.sample(vox, times, sampler=sampler, seed=1)
        assert np.all(np.diff(back["t"]) >= 0), sampler
        same_seed = v2ce.sample(vox, times, sampler=sampler, seed=1)
        assert np.array_equal(back, same_seed), sampler
        if sampler in ("even", "random"):
            # The paper's baselines draw floor(v) events plus a Bernoulli one per node.
            assert abs(len(back) - len(events)) < 0.02 * len(events), sampler
            continue
        # Every cell keeps its count: the same events per pixel and polarity (an event re-timed
        # onto an interval's end is voxelized into the next, so compare over all intervals).
        assert len(back) == len(events), sampler
        again = v2ce.voxelize(back, times, bins=10)
        per_cell = lambda v: v.reshape(7, 2, 10, 48, 64).sum(axis=(0, 2))
        assert np.allclose(per_cell(again), per_cell(vox), atol=1e-3), sampler
    report = v2ce.eval_stage2(events, times, sampler="moment")
    assert report["sampler"] == "moment" and report["pger"] == 1.0
    report = v2ce.eval_stage2(events, times)
    assert report["sampler"] == "spatial" and report["pger"] == 1.0
    with pytest.raises(ValueError, match="voxel grids"):
        v2ce.sample(vox, times[:5])
    with pytest.raises(ValueError):
        v2ce.sample(vox, times, sampler="sideways")


def test_eval_stage1_is_the_cli_on_davis346(tmp_path):
    clip = shared_data() / "davis346" / "davis346.aedat4"
    real = v2ce.read(clip)
    sim = v2ce.convert(clip, seed=1)
    v2ce.write(tmp_path / "sim.aedat4", sim)
    out = cli("eval", "stage1", "--real", clip, "--sim", tmp_path / "sim.aedat4", "--json")
    import json

    want = json.loads(out.stdout)
    frames = v2ce_frame_times(clip)
    got = v2ce.eval_stage1(real, sim, frames)
    for key in ("tf1", "tpf1", "rf1", "c_mete_us", "pger", "real_events", "sim_events"):
        assert got[key] == pytest.approx(want[key]), key
    # A stream scored against itself is perfect.
    assert v2ce.eval_stage1(real, real, frames)["tf1"] == pytest.approx(1.0)


def v2ce_frame_times(clip):
    """The APS frame times the CLI scores on: each frame's mid-exposure."""
    import aedat

    times = []
    for packet in aedat.Decoder(str(clip)):
        if "frame" in packet:
            f = packet["frame"]
            b, e = f["exposure_begin_t"], f["exposure_end_t"]
            times.append(b + (e - b) // 2 if e >= b > 0 else f["t"])
    return np.asarray(times, np.int64)


def test_the_gil_is_released_while_the_core_works():
    import threading

    done = threading.Event()
    result = {}

    def work():
        result["events"] = v2ce.convert("fixture", max_frames=45)
        done.set()

    worker = threading.Thread(target=work)
    worker.start()
    spins = 0
    while not done.is_set():
        spins += 1
    worker.join()
    # Held through the conversion, the GIL would have stopped this loop for its whole length.
    assert len(result["events"]) > 0
    assert spins > 100_000, spins


def test_sizes_from_outside_are_bounded_before_allocating():
    with pytest.raises(ValueError):
        v2ce.Simulator(65535, 65535)
    with pytest.raises(ValueError, match="frames"):
        v2ce.convert(np.zeros((2, 8193, 1), np.uint8), times_us=np.array([0, 1], np.int64))
    events = np.zeros(1, v2ce.EVENT_DTYPE)
    with pytest.raises(ValueError, match="voxel tensor|GB"):
        v2ce.voxelize(events, np.arange(0, 100_000_000, 1000, dtype=np.int64), bins=1000,
                      size=(8192, 8192))
    with pytest.raises(ValueError):
        v2ce.sample(np.zeros((1, 3, 4, 4), np.float32), np.array([0, 10], np.int64))


def test_extreme_times_are_refused_not_wrapped():
    frames = moving_bar(n=2)
    for times in (
        [-9_223_372_036_854_000_000, 9_223_372_036_854_000_000],
        [0, 2**62],
        [0, 2**53 + 1],
        [np.nan, 9.2e18],
        [0, np.inf],
        [5, 5],
        [5, 4],
    ):
        with pytest.raises(ValueError):
            v2ce.convert(frames, times_us=np.array(times))
    sim = v2ce.Simulator(64, 48)
    sim.push(frames[0], 0)
    for t in (2**62, 2**53 + 1, float("nan"), -1):
        with pytest.raises(ValueError):
            sim.push(frames[1], t)
    assert isinstance(sim.push(frames[1], 10_000), np.ndarray)
    events = np.zeros(2, v2ce.EVENT_DTYPE)
    events["t"] = [0, 10]
    for times in ([0, 2**62], [-(2**62), 0], [0, 2**53 + 1]):
        with pytest.raises(ValueError):
            v2ce.eval_stage2(events, np.array(times, np.int64), size=(8, 8))
        with pytest.raises(ValueError):
            v2ce.voxelize(events, np.array(times, np.int64), size=(8, 8))


def test_write_refuses_values_a_cast_would_change(tmp_path):
    good = np.zeros(2, v2ce.EVENT_DTYPE)
    good["t"] = [0, 10]
    v2ce.write(tmp_path / "ok.csv", good, size=(8, 8))
    columns = {"t": np.array([0, 10], np.int64), "x": np.array([1, 2], np.int32),
               "y": np.array([1, 2], np.int32), "p": np.array([1, 0], np.int8)}
    bad = [("x", np.array([-1, 65539], np.int32)), ("y", np.array([0, 70000], np.int64)),
           ("t", np.array([0, np.nan])), ("t", np.array([0.0, 1e19])),
           ("x", np.array([0.5, 1.0]))]
    for name, values in bad:
        arrays = dict(columns, **{name: values})
        dtype = [(k, v.dtype) for k, v in arrays.items()]
        events = np.zeros(2, dtype)
        for k, v in arrays.items():
            events[k] = v
        with pytest.raises(ValueError, match=name):
            v2ce.write(tmp_path / f"bad-{name}.csv", events, size=(65535, 65535))
        assert not (tmp_path / f"bad-{name}.csv").exists()


def test_settings_that_contain_themselves_are_refused():
    frames = moving_bar(n=2)
    times = np.array([0, 10_000], np.int64)
    loop = []
    loop.append(loop)
    deep = {}
    d = deep
    for _ in range(100_000):
        d["a"] = {}
        d = d["a"]
    for value in (loop, deep):
        with pytest.raises(ValueError, match="deep"):
            v2ce.convert(frames, times_us=times, foo=value)


def test_threads_sharing_a_simulator_or_reader_take_turns(tmp_path):
    import threading

    frames = moving_bar(n=40)
    sim = v2ce.Simulator(64, 48)
    sim.push(frames[0], 0)
    clock = iter(range(1, 10**6))
    lock = threading.Lock()
    errors = []

    def push_many():
        for k in range(1, 40):
            with lock:
                t = next(clock) * 1000
            try:
                sim.push(frames[k], t)
            except ValueError as e:
                # Another thread's later frame got there first: refused, never a hang.
                if "does not come after" not in str(e):
                    errors.append(e)

    path = tmp_path / "r.aedat4"
    v2ce.write(path, v2ce.convert(frames, times_us=np.arange(40, dtype=np.int64) * 10_000),
               size=(64, 48))
    reader = v2ce.open(path)

    def read_many():
        for chunk in reader.chunks(7):
            if not (len(chunk) > 0 and reader.size == (64, 48)):
                errors.append((len(chunk), reader.size))

    threads = [threading.Thread(target=push_many) for _ in range(4)]
    threads += [threading.Thread(target=read_many) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=60)
    assert not any(th.is_alive() for th in threads), "threads still waiting: a deadlock"
    assert not errors, errors


def test_voxels_that_imply_too_many_events_are_refused():
    times = np.array([0, 10_000], np.int64)
    one = np.zeros((1, 20, 8, 8), np.float32)
    one[0, 3, 2, 2] = 1e12
    with pytest.raises(ValueError, match="above"):
        v2ce.sample(one, times)
    # 1e6 per node (the most one may hold) over 64 x 64 x 20 nodes: 82 billion events.
    with pytest.raises(ValueError, match="GB"):
        v2ce.sample(np.full((1, 20, 64, 64), 1e6, np.float32), times)
