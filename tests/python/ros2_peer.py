"""A ROS 2 peer without ROS: Cyclone DDS (PyPI `cyclonedds`, the DDS of `rmw_cyclonedds`)
subscribing to v2ce's EventPacket topic and publishing sensor_msgs/msg/Image frames, and
rosbags (PyPI) reading and writing .mcap bags. Used by tests/ros2.rs.

  ros2_peer.py subscribe TOPIC OUT.raw SECONDS [--start-after N]
      Writes the concatenated EVT 3.0 payloads (behind a RAW header) to OUT.raw and a JSON
      summary (packets, seqs, widths, stamps, per-packet faery decode ok) to OUT.raw.json.
  ros2_peer.py publish TOPIC FRAMES.npz [--hostile]
      Publishes the frames (uint8 gray, times in us) as mono8 Images, then (with --hostile)
      malformed ones.
  ros2_peer.py bag-read BAG.mcap OUT.raw      EventPacket payloads of a bag, decoded as above.
  ros2_peer.py bag-write FRAMES.npz BAG.mcap TOPIC   Images into a bag with rosbags.
  ros2_peer.py frames FRAMES.npz FOLDER      The test frames, also as PNGs with times.txt.
"""
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def dds_types():
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.types import uint32, uint64, int32, uint8, sequence
    import cyclonedds.idl.annotations as annotate

    @dataclass
    @annotate.final
    class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
        sec: int32
        nanosec: uint32

    @dataclass
    @annotate.final
    class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
        stamp: Time
        frame_id: str

    @dataclass
    @annotate.final
    class EventPacket(IdlStruct, typename="event_camera_msgs::msg::dds_::EventPacket_"):
        header: Header
        height: uint32
        width: uint32
        seq: uint64
        time_base: uint64
        encoding: str
        is_bigendian: bool
        events: sequence[uint8]

    @dataclass
    @annotate.final
    class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
        header: Header
        height: uint32
        width: uint32
        encoding: str
        is_bigendian: uint8
        step: uint32
        data: sequence[uint8]

    return Time, Header, EventPacket, Image


def raw_header(width, height):
    text = "%% evt 3.0\n%% format EVT3;height=%d;width=%d\n%% geometry %dx%d\n%% end\n" % (
        height, width, width, height)
    return text.encode()


def faery_decode(path):
    import faery
    n = 0
    ts = []
    for packet in faery.events_stream_from_file(path):
        n += len(packet)
        if len(packet):
            ts.append(int(packet["t"][0]))
    return n


def write_raw(packets, out):
    width = packets[0]["width"] if packets else 640
    height = packets[0]["height"] if packets else 480
    with open(out, "wb") as f:
        f.write(raw_header(width, height))
        for p in packets:
            f.write(p["events"])


def check_alone(packets, out):
    """Each packet decoded alone by faery: the count it holds."""
    counts = []
    for i, p in enumerate(packets[:50]):
        one = str(out) + ".one.raw"
        write_raw([p], one)
        counts.append(faery_decode(one))
        Path(one).unlink()
    return counts


def subscribe(topic, out, seconds, start_after=0):
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.topic import Topic
    from cyclonedds.sub import DataReader
    from cyclonedds.core import Qos, Policy
    from cyclonedds.util import duration
    _, _, EventPacket, _ = dds_types()
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    t = Topic(dp, "rt/" + topic.lstrip("/"), EventPacket)
    qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10000))
    reader = DataReader(dp, t, qos=qos)
    print("ready", flush=True)
    packets = []
    end = time.time() + seconds
    quiet_since = None
    seen = 0
    while time.time() < end:
        got = reader.take(1000)
        if any(hasattr(s, "seq") for s in got) and seen == 0:
            print("first", flush=True)
        # A writer that went away reaches a reader as an invalid sample (no data): skipped.
        got = [s for s in got if hasattr(s, "seq")]
        for s in got:
            seen += 1
            if seen <= start_after:
                continue
            packets.append({"seq": int(s.seq), "width": int(s.width), "height": int(s.height),
                            "stamp": [int(s.header.stamp.sec), int(s.header.stamp.nanosec)],
                            "frame_id": s.header.frame_id, "encoding": s.encoding,
                            "time_base": int(s.time_base), "events": bytes(s.events)})
        if got:
            quiet_since = None
        elif packets:
            quiet_since = quiet_since or time.time()
            if time.time() - quiet_since > 3:
                break
        time.sleep(0.01)
    write_raw(packets, out)
    summary = {
        "packets": len(packets),
        "seqs": [p["seq"] for p in packets],
        "stamps": [p["stamp"] for p in packets],
        "frame_ids": sorted({p["frame_id"] for p in packets}),
        "encodings": sorted({p["encoding"] for p in packets}),
        "sizes": sorted({(p["width"], p["height"]) for p in packets}),
        "alone": check_alone(packets, out),
        "faery_events": faery_decode(out) if packets else 0,
    }
    Path(str(out) + ".json").write_text(json.dumps(summary))


def publish(topic, frames_path, hostile=False, first=0, last=None, flood=False, twice=False):
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.topic import Topic
    from cyclonedds.pub import DataWriter
    from cyclonedds.core import Qos, Policy
    from cyclonedds.util import duration
    Time, Header, _, Image = dds_types()
    data = np.load(frames_path)
    frames, times = data["frames"][first:last], data["t_us"][first:last]
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    t = Topic(dp, "rt/" + topic.lstrip("/"), Image)
    junk_writer = None
    if hostile:
        # Bytes that are no Image under the Image type name: a second participant's writer of
        # another layout (Cyclone checks nothing of the reader's, which takes raw CDR).
        from cyclonedds.idl import IdlStruct
        from cyclonedds.idl.types import sequence, uint8

        @dataclass
        class Junk(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
            junk: sequence[uint8]

        dp2 = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
        junk_writer = DataWriter(dp2, Topic(dp2, "rt/" + topic.lstrip("/"), Junk),
                                 qos=Qos(Policy.Reliability.Reliable(duration(seconds=5)),
                                         Policy.History.KeepLast(100)))
    qos = Qos(Policy.Reliability.Reliable(duration(seconds=5)), Policy.History.KeepLast(1000))
    writer = DataWriter(dp, t, qos=qos)
    # Wait for v2ce's reader (and the junk writer's match, where there is one).
    for _ in range(500):
        if writer.get_matched_subscriptions() and (
                junk_writer is None or junk_writer.get_matched_subscriptions()):
            break
        time.sleep(0.02)
    print("matched", len(writer.get_matched_subscriptions()), flush=True)
    time.sleep(0.5)

    def image(i, t_us, arr, encoding="mono8", step=None, data=None, width=None, height=None):
        h, w = arr.shape[:2]
        sec, usec = divmod(int(t_us), 1_000_000)
        return Image(header=Header(stamp=Time(sec=sec, nanosec=usec * 1000), frame_id="camera"),
                     height=h if height is None else height, width=w if width is None else width,
                     encoding=encoding, is_bigendian=0,
                     step=(w if step is None else step),
                     data=list(arr.tobytes()) if data is None else data)

    if twice:
        # A bag played in a loop: the same frames again, their stamps back at the start.
        frames = np.concatenate([frames, frames])
        times = np.concatenate([times, times])
    for i, (f, t_us) in enumerate(zip(frames, times)):
        if hostile and i == len(frames) // 2:
            g = frames[0]
            h, w = g.shape
            # Each of these must be refused, counted, and the daemon must go on.
            writer.write(image(i, t_us, g, step=w - 1))                 # step shorter than a row
            writer.write(image(i, t_us, g, data=list(g.tobytes()[:-5])))  # data shorter than step x height
            writer.write(image(i, t_us, g, encoding="bayer_rggb8"))      # an encoding not read
            writer.write(image(i, t_us, g, width=w * 2))                  # size disagrees with data
            writer.write(image(i, int(times[0]), g))                      # a stamp that goes back
            writer.write(image(i, t_us + 3600 * 10**6, g))                # a stamp an hour ahead
            writer.write(image(i, t_us, g, width=100000, height=100000, step=100000))  # absurd size
            junk_writer.write(Junk(junk=[0xFF] * 37))                    # malformed CDR
            time.sleep(0.2)
        writer.write(image(i, t_us, f))
        if not flood:
            time.sleep(0.01)
    time.sleep(2)
    print("published", len(frames), flush=True)


def gray_png(a):
    """An 8-bit gray PNG of `a` (no dependency beyond the standard library)."""
    import struct
    import zlib

    def chunk(kind, data):
        c = struct.pack(">I", len(data)) + kind + data
        return c + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    h, w = a.shape
    raw = b"".join(b"\x00" + a[r].tobytes() for r in range(h))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def make_frames(out_npz, folder):
    """A bright bar crossing a textured 160x120 scene: 40 mono8 frames 33.333 ms apart from
    t = 1 s, as an .npz (frames, t_us) and as a PNG folder with times.txt."""
    h, w, n = 120, 160, 40
    yy, xx = np.mgrid[0:h, 0:w]
    frames, times = [], []
    for i in range(n):
        f = 40 + 30 * np.sin(xx / 7.0) * np.cos(yy / 9.0)
        x0 = 10 + 3 * i
        f[:, x0:x0 + 12] = 220
        frames.append(np.clip(f, 0, 255).astype(np.uint8))
        times.append(1_000_000 + (i * 100_000) // 3)
    frames = np.stack(frames)
    np.savez(out_npz, frames=frames, t_us=np.array(times, dtype=np.int64))
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        (folder / ("%04d.png" % i)).write_bytes(gray_png(f))
    (folder / "times.txt").write_text("".join("%.6f\n" % (t / 1e6) for t in times))


def publish_packets(topic):
    """EventPackets for `v2ce listen --ros2`: two good ones (seq 0 and 2: one missing), then
    hostile ones (an encoding not read, words cut in half, a sensor of width 0, an event off
    the sensor)."""
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.topic import Topic
    from cyclonedds.pub import DataWriter
    from cyclonedds.core import Qos, Policy
    from cyclonedds.util import duration
    Time, Header, EventPacket, _ = dds_types()
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    t = Topic(dp, "rt/" + topic.lstrip("/"), EventPacket)
    writer = DataWriter(dp, t, qos=Qos(Policy.Reliability.Reliable(duration(seconds=5)),
                                       Policy.History.KeepLast(100)))
    for _ in range(500):
        if writer.get_matched_subscriptions():
            break
        time.sleep(0.02)
    time.sleep(0.5)

    def words(*ws):
        return list(np.array(ws, dtype="<u2").tobytes())

    def packet(seq, events, encoding="evt3", width=64, height=32):
        return EventPacket(header=Header(stamp=Time(sec=1, nanosec=seq * 1000), frame_id="x"),
                           height=height, width=width, seq=seq, time_base=0, encoding=encoding,
                           is_bigendian=False, events=events)
    # time high 0, time low 5, row 3, x 7 ON; then x 9 OFF
    good = words(0x8000, 0x6005, 0x0003, 0x2807, 0x2009)
    writer.write(packet(0, good))
    writer.write(packet(2, good))
    writer.write(packet(3, good, encoding="mono"))
    writer.write(packet(4, good[:-1]))
    writer.write(packet(5, good, width=0))
    writer.write(packet(6, words(0x8000, 0x6005, 0x0003, 0x2800 | 100)))
    time.sleep(2)
    print("published", flush=True)


def bag_read(bag, out):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_HUMBLE)
    packets = []
    with AnyReader([Path(bag)], default_typestore=ts) as r:
        for con, _, raw in r.messages():
            if con.msgtype != "event_camera_msgs/msg/EventPacket":
                continue
            m = r.deserialize(raw, con.msgtype)
            packets.append({"width": int(m.width), "height": int(m.height), "seq": int(m.seq),
                            "stamp": [int(m.header.stamp.sec), int(m.header.stamp.nanosec)],
                            "events": bytes(m.events)})
    write_raw(packets, out)
    Path(str(out) + ".json").write_text(json.dumps({
        "packets": len(packets), "seqs": [p["seq"] for p in packets],
        "faery_events": faery_decode(out) if packets else 0}))


def bag_write(frames_path, bag, topic):
    from rosbags.rosbag2 import Writer, StoragePlugin
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_HUMBLE)
    Image = ts.types["sensor_msgs/msg/Image"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    data = np.load(frames_path)
    frames, times = data["frames"], data["t_us"]
    bag = Path(bag)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        con = w.add_connection(topic, "sensor_msgs/msg/Image", typestore=ts)
        other = w.add_connection("/other", "sensor_msgs/msg/Image", typestore=ts)
        for f, t_us in zip(frames, times):
            sec, usec = divmod(int(t_us), 1_000_000)
            h, wd = f.shape
            msg = Image(header=Header(stamp=Time(sec=sec, nanosec=usec * 1000), frame_id="camera"),
                        height=h, width=wd, encoding="mono8", is_bigendian=0, step=wd,
                        data=np.frombuffer(f.tobytes(), dtype=np.uint8))
            raw = ts.serialize_cdr(msg, "sensor_msgs/msg/Image")
            w.write(con, int(t_us) * 1000, raw)
            # A second camera on another topic, which --topic leaves out.
            w.write(other, int(t_us) * 1000, ts.serialize_cdr(
                Image(header=msg.header, height=2, width=2, encoding="mono8", is_bigendian=0,
                      step=2, data=np.zeros(4, dtype=np.uint8)), "sensor_msgs/msg/Image"))


if __name__ == "__main__":
    cmd = sys.argv[1]
    if cmd == "subscribe":
        start_after = 0
        if "--start-after" in sys.argv:
            start_after = int(sys.argv[sys.argv.index("--start-after") + 1])
        subscribe(sys.argv[2], sys.argv[3], float(sys.argv[4]), start_after)
    elif cmd == "publish":
        def opt(name, default):
            return int(sys.argv[sys.argv.index(name) + 1]) if name in sys.argv else default
        publish(sys.argv[2], sys.argv[3], "--hostile" in sys.argv, opt("--first", 0),
                opt("--last", None), "--flood" in sys.argv, "--twice" in sys.argv)
    elif cmd == "publish-packets":
        publish_packets(sys.argv[2])
    elif cmd == "bag-read":
        bag_read(sys.argv[2], sys.argv[3])
    elif cmd == "frames":
        make_frames(sys.argv[2], sys.argv[3])
    elif cmd == "bag-write":
        bag_write(sys.argv[2], sys.argv[3], sys.argv[4])
    else:
        sys.exit("unknown command " + cmd)
