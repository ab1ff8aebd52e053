"""Independent readers check what v2ce writes and sends.

Run by the Rust integration tests (tests/independent_readers.rs) with the project's virtual
environment; each mode compares what a third-party reader gets with an expected CSV
(`t_us,x,y,on`) and exits 0 on an exact match, 1 on a mismatch, 2 on a timeout.

    crosscheck.py files READER PATH EXPECTED.csv [PATH EXPECTED.csv ...]   each pair, offset 0
    crosscheck.py prom METRICS.txt   parses Prometheus text with prometheus_client's parser and
                                     prints every sample as JSON lines {name, labels, value}
    crosscheck.py file READER PATH EXPECTED.csv [T_OFFSET]   READER: faery | aedat | dv |
                                                               aestream | expelliarmus |
                                                               numpy | h5py
    crosscheck.py udp FORMAT PORT EXPECTED.csv WIDTH HEIGHT    FORMAT: t64_x16_y16_on8 |
                                                               t32_x16_y15_on1 | spif
    crosscheck.py tcp PORT EXPECTED.csv
    crosscheck.py aestream PORT EXPECTED.csv WIDTH HEIGHT [LOSS]   aestream's UDP receiver (spif);
                                                               EXPECTED may be written later

`udp` and `tcp` print READY once listening (udp) or connected (tcp).
"""

import os
import socket
import sys
import threading

import numpy as np
from pathlib import Path


def expected(path):
    data = np.loadtxt(path, delimiter=",", skiprows=1, dtype=np.int64, ndmin=2)
    if data.size == 0:
        return np.zeros((0, 4), dtype=np.int64)
    return data


def columns(t, x, y, on):
    return np.stack(
        [np.asarray(t, np.int64), np.asarray(x, np.int64), np.asarray(y, np.int64),
         np.asarray(on, np.int64)],
        axis=1,
    )


def compare(got, want, what):
    if got.shape == want.shape and np.array_equal(got, want):
        print(f"OK {what}: {len(got)} events identical")
        return 0
    print(f"MISMATCH {what}: got {len(got)} events, expected {len(want)}")
    n = min(len(got), len(want))
    bad = np.nonzero(np.any(got[:n] != want[:n], axis=1))[0]
    if len(bad):
        i = bad[0]
        print(f"first difference at {i}: got {got[i].tolist()} expected {want[i].tolist()}")
    return 1


def read_faery(path):
    import faery

    arr = faery.events_stream_from_file(path).to_array()
    return columns(arr["t"], arr["x"], arr["y"], arr["on"])


def read_aedat(path):
    import aedat

    parts = []
    for packet in aedat.Decoder(path):
        if "events" in packet:
            e = packet["events"]
            parts.append(columns(e["t"], e["x"], e["y"], e["on"]))
    return np.concatenate(parts) if parts else np.zeros((0, 4), np.int64)


def read_dv(path):
    import dv_processing as dv

    rec = dv.io.MonoCameraRecording(path)
    parts = []
    while rec.isRunning():
        batch = rec.getNextEventBatch()
        if batch is None:
            break
        if len(batch) > 0:
            e = batch.numpy()
            parts.append(columns(e["timestamp"], e["x"], e["y"], e["polarity"]))
    return np.concatenate(parts) if parts else np.zeros((0, 4), np.int64)


def read_aestream(path):
    """aestream 0.6.4's file reader (AEDAT 4.0; it reads every .raw as EVT 3.0, which fails on
    EVT 2.0 files, Prophesee's own sample included, and mis-times EVT 3.0)."""
    import aestream

    e = aestream.FileInput(path, (1024, 1024)).load()
    return columns(e["timestamp"], e["x"], e["y"], e["polarity"])


def read_expelliarmus(path):
    """expelliarmus (tonic's RAW reader): the encoding from the file's `% evt` header."""
    import expelliarmus

    with open(path, "rb") as f:
        head = f.read(4096).decode("latin-1")
    encoding = "evt3" if "% evt 3" in head else "evt2"
    e = expelliarmus.Wizard(encoding=encoding).read(path)
    return columns(e["t"], e["x"], e["y"], e["p"])


def read_numpy(path):
    """The V2CE toolbox's .npz, as np.load reads it."""
    e = np.load(path)["event_stream"]
    return columns(e["timestamp"], e["x"], e["y"], e["polarity"])


def read_h5py(path):
    """An HDF5 file in the DSEC layout, as h5py reads it: events/{x,y,t,p} plus t_offset, with
    ms_to_idx checked against the times (entry m is the first event at or after m ms)."""
    import h5py

    with h5py.File(path, "r") as f:
        x, y, t, p = (f["events"][k][()] for k in ("x", "y", "t", "p"))
        t_offset = int(f["t_offset"][()])
        ms_to_idx = f["ms_to_idx"][()]
    if not (len(x) == len(y) == len(t) == len(p)):
        raise SystemExit(f"events/x,y,t,p lengths differ: {len(x)} {len(y)} {len(t)} {len(p)}")
    stored = t.dtype
    t = t.astype(np.int64)
    if np.any(np.diff(t) < 0):
        raise SystemExit("events/t is not sorted")
    last_ms = int(t[-1]) // 1000 if len(t) else -1
    want = np.searchsorted(t, np.arange(last_ms + 1, dtype=np.int64) * 1000, side="left")
    if not np.array_equal(ms_to_idx.astype(np.int64), want):
        raise SystemExit(f"ms_to_idx ({len(ms_to_idx)} entries) is not the events' index "
                         f"({len(want)} entries)")
    print(f"ms_to_idx consistent: {len(ms_to_idx)} ms; events/t is {stored}")
    return columns(t + t_offset, x, y, p)


def read_rosbags(path):
    """A rosbag2 .mcap as rosbags reads it: its event_camera_msgs/msg/EventPacket messages
    (evt3), whose payloads end to end are one EVT 3.0 stream, decoded by faery behind a RAW
    header; each event's time is its packet's stamp plus its sensor time less the packet's
    first (the stamps are the event times)."""
    import tempfile

    import faery
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    payloads, size = [], None
    with AnyReader([Path(path)], default_typestore=store) as r:
        for con, _, raw in r.messages():
            if con.msgtype != "event_camera_msgs/msg/EventPacket":
                continue
            m = r.deserialize(raw, con.msgtype)
            if m.encoding != "evt3":
                raise SystemExit(f"encoding {m.encoding}")
            size = (int(m.width), int(m.height))
            payloads.append(bytes(m.events))
    if not payloads:
        return columns([], [], [], [])
    with tempfile.NamedTemporaryFile(suffix=".raw", delete=False) as f:
        f.write(("%% evt 3.0\n%% geometry %dx%d\n%% end\n" % size).encode())
        for p in payloads:
            f.write(p)
    try:
        arr = faery.events_stream_from_file(f.name).to_array()
    finally:
        os.unlink(f.name)
    return columns(arr["t"], arr["x"], arr["y"], arr["on"])


READERS = {
    "numpy": read_numpy,
    "rosbags": read_rosbags,
    "h5py": read_h5py,
    "faery": read_faery,
    "aedat": read_aedat,
    "dv": read_dv,
    "aestream": read_aestream,
    "expelliarmus": read_expelliarmus,
}


def watchdog(seconds, what):
    def fire():
        print(f"TIMEOUT {what} after {seconds} s", flush=True)
        os._exit(2)

    timer = threading.Timer(seconds, fire)
    timer.daemon = True
    timer.start()


def decode_spif(datagram):
    """SPIF words, little-endian: bit 31 set = no timestamp word follows; bits 30..16 x;
    bit 15 polarity; bits 14..0 y. With bit 31 clear, the next word is the time (u32 us)."""
    words = np.frombuffer(datagram[: len(datagram) // 4 * 4], dtype="<u4")
    out = []
    i = 0
    while i < len(words):
        w = int(words[i])
        t = -1
        if not w >> 31:
            t = int(words[i + 1])
            i += 1
        out.append((t, (w >> 16) & 0x7FFF, w & 0x7FFF, (w >> 15) & 1))
        i += 1
    return out


def udp(fmt, port, want, width, height):
    watchdog(30, f"udp {fmt}")
    if fmt == "spif":
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", port))
        print("READY", flush=True)
        rows = []
        largest = 0
        while len(rows) < len(want):
            datagram = sock.recv(65536)
            largest = max(largest, len(datagram))
            rows.extend(decode_spif(datagram))
        print(f"largest datagram {largest} bytes")
        got = np.array(rows, dtype=np.int64).reshape(-1, 4)
        if (got[:, 0] >= 0).all():
            want = want.copy()
            want[:, 0] %= 1 << 32
        else:
            got[:, 0] = want[: len(got), 0]  # no timestamps sent: compare addresses only
        return compare(got, want, "spif over UDP")
    import faery

    import faery.udp_decoder

    bound = threading.Event()
    original_init = faery.udp_decoder.Receiver.__init__

    def init_and_signal(self, *args, **kwargs):
        original_init(self, *args, **kwargs)
        bound.set()

    faery.udp_decoder.Receiver.__init__ = init_and_signal
    decoder = faery.events_stream_from_udp((width, height), ("127.0.0.1", port), format=fmt)
    parts = []
    done = threading.Event()

    def consume():
        count = 0
        for packet in decoder:
            parts.append(columns(packet["t"], packet["x"], packet["y"], packet["on"]))
            count += len(packet)
            if count >= len(want):
                break
        done.set()

    threading.Thread(target=consume, daemon=True).start()
    # faery binds its socket when iteration starts: say READY once it has.
    bound.wait()
    print("READY", flush=True)
    done.wait()
    got = np.concatenate(parts)
    if fmt == "t32_x16_y15_on1":
        want = want.copy()
        want[:, 0] %= 1 << 32
        got[:, 0] %= 1 << 32
    return compare(got, want, f"faery {fmt} over UDP")


def tcp(port, want):
    import dv_processing as dv

    watchdog(30, "tcp")
    reader = dv.io.NetworkReader("127.0.0.1", port)
    print("READY", flush=True)
    size = reader.getEventResolution()
    parts = []
    count = 0
    while count < len(want):
        batch = reader.getNextEventBatch()
        if batch is None or len(batch) == 0:
            if not reader.isRunning():
                break
            continue
        e = batch.numpy()
        parts.append(columns(e["timestamp"], e["x"], e["y"], e["polarity"]))
        count += len(batch)
    print(f"resolution {size}")
    got = np.concatenate(parts) if parts else np.zeros((0, 4), np.int64)
    return compare(got, want, "dv_processing NetworkReader over TCP")


# The most events one 512-byte datagram (what aestream reads of each) carries: 4-byte SPIF words.
MAX_EVENTS_PER_DATAGRAM = 512 // 4


def udp_drops(port):
    """Datagrams the kernel dropped for want of room in the receive buffers of the sockets bound
    to `port` (the `drops` column of /proc/net/udp and /proc/net/udp6): what a receiver that got
    no core for a while loses, which the sender cannot see."""
    total = 0
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        try:
            with open(table) as f:
                lines = f.read().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) > 12 and int(fields[1].rsplit(":", 1)[1], 16) == port:
                total += int(fields[-1])
    return total


def aestream_udp(port, want_path, width, height, allowed_loss=0.0):
    """aestream's UDP receiver (its C++ socket reads 512 bytes per datagram) accumulating
    per-pixel counts, as its PyTorch/Norse/snnTorch users get them, against the expected
    events' per-pixel counts (all polarities). `allowed_loss` is the fraction of events that may
    be missing in all (datagrams the kernel dropped when the receiving thread got no core); no
    pixel may ever get more events than expected. When `want_path` does not exist yet (the
    sender's own recording of what it sends), the stream is read until it has been quiet for
    3 s and the file is read then."""
    import time

    import aestream

    watchdog(120, "aestream udp")
    want = expected(want_path) if os.path.exists(want_path) else None
    got = np.zeros((width, height), np.int64)
    last = None
    with aestream.UDPInput((width, height), device="cpu", port=port) as stream:
        print("READY", flush=True)
        while want is None or got.sum() < len(want):
            frame = np.asarray(stream.read()).astype(np.int64)
            if frame.sum():
                got += frame
                last = time.monotonic()
            elif last is not None and time.monotonic() - last > 3:
                break
            time.sleep(0.002)
        # Read while the socket is open: its counter goes with it.
        drops = udp_drops(port)
    if want is None:
        want = expected(want_path)
    expect = np.zeros((width, height), np.int64)
    np.add.at(expect, (want[:, 1], want[:, 2]), 1)
    if np.array_equal(got, expect):
        print(f"OK aestream: {got.sum()} of {len(want)} events, every pixel's count identical")
        return 0
    bad = np.argwhere(got != expect)
    x, y = bad[0]
    missing = len(want) - got.sum()
    if (got <= expect).all() and missing <= allowed_loss * len(want):
        print(f"OK aestream: {got.sum()} of {len(want)} events ({missing / len(want):.4%} lost, "
              f"allowed {allowed_loss:.2%}), no pixel over its count")
        return 0
    # Every event missing is accounted for by a datagram the kernel dropped at the receiver
    # (its buffer full while aestream's thread had no core): everything sent was delivered to
    # the receiver's socket, which is what the sender can guarantee.
    if (got <= expect).all() and 0 < drops and missing <= drops * MAX_EVENTS_PER_DATAGRAM:
        print(f"OK aestream: {got.sum()} of {len(want)} events; the {missing} missing are in the "
              f"{drops} datagrams the kernel dropped at the receiver (a full buffer: the receiving "
              f"thread got no core), no pixel over its count")
        return 0
    print(f"MISMATCH aestream: {got.sum()} of {len(want)} events; {len(bad)} pixels differ, "
          f"first ({x}, {y}): got {got[x, y]} expected {expect[x, y]}; the kernel dropped {drops} "
          f"datagrams at the receiver")
    return 1


def main(argv):
    mode = argv[1]
    if mode == "file":
        reader, path, want = argv[2], argv[3], expected(argv[4])
        offset = int(argv[5]) if len(argv) > 5 else 0
        watchdog(120, f"{reader} reading {path}")
        got = READERS[reader](path)
        got[:, 0] += offset
        return compare(got, want, f"{reader} reading {os.path.basename(path)}")
    if mode == "prom":
        import json
        from prometheus_client.parser import text_string_to_metric_families

        with open(argv[2]) as f:
            text = f.read()
        for family in text_string_to_metric_families(text):
            for sample in family.samples:
                print(json.dumps({"family": family.name, "type": family.type,
                                  "name": sample.name, "labels": sample.labels,
                                  "value": sample.value}))
        return 0
    if mode == "files":
        reader, pairs = argv[2], argv[3:]
        watchdog(600, f"{reader} reading {len(pairs) // 2} files")
        failed = 0
        for path, want in zip(pairs[0::2], pairs[1::2]):
            try:
                got = READERS[reader](path)
            except Exception as e:  # a reader that raises is a failure of this file
                print(f"FAILED {reader} reading {path}: {type(e).__name__}: {e}")
                failed += 1
                continue
            failed += compare(got, expected(want), f"{reader} reading {path}")
        return 1 if failed else 0
    if mode == "udp":
        return udp(argv[2], int(argv[3]), expected(argv[4]), int(argv[5]), int(argv[6]))
    if mode == "aestream":
        allowed_loss = float(argv[6]) if len(argv) > 6 else 0.0
        return aestream_udp(int(argv[2]), argv[3], int(argv[4]), int(argv[5]), allowed_loss)
    if mode == "tcp":
        return tcp(int(argv[2]), expected(argv[3]))
    print(f"unknown mode {mode}")
    return 3


if __name__ == "__main__":
    sys.exit(main(sys.argv))
