"""The `record` executable against real rclpy publishers (isolated DDS domain, see conftest.py).

A recorder process records contract topics published from this test process; the bag must
hold exactly the published bytes, open with independent readers (the `mcap` library and
rosbags' AnyReader) and decode as the contract types; SIGINT closes it cleanly, SIGKILL
leaves a bag that `sep_control.bags` still reads up to the last flush; it stops by itself at the end.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bag_synth import TYPES, small_scenario, synthetic_episode, episode_messages
from sep_plant import topics as T

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parent.parent
SRC = os.pathsep.join(str(REPO / p) for p in ("sep_plant", "sep_estimator", "sep_control"))


def start_recorder(out: Path, *args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""), PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "sep_control.ros.record_node", "--out", str(out), *args],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            stdin=subprocess.DEVNULL)


@pytest.fixture
def ros():
    import rclpy
    from rclpy.node import Node

    ctx = rclpy.Context()
    ctx.init()
    node = Node("sep_test_publisher", context=ctx)
    yield node
    node.destroy_node()
    ctx.shutdown()


def _msg_class(msgtype):
    from sep_control.ros.record_node import _msg_class

    return _msg_class(msgtype)


def make_publishers(node, topics):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    pubs = {}
    for t in topics:
        tl = t.endswith("/scenario")
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if tl else DurabilityPolicy.VOLATILE)
        pubs[t] = node.create_publisher(_msg_class(TYPES[t]), t, qos)
    return pubs


def wait_matched(pubs, proc, timeout=30.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if all(p.get_subscription_count() > 0 for p in pubs.values()):
            return
        if proc.poll() is not None:
            raise AssertionError(f"recorder exited early: {proc.communicate()}")
        time.sleep(0.05)
    raise AssertionError("recorder did not subscribe in time")


def publish_all(pubs, msgs, pause=0.0):
    sent: dict[str, list[bytes]] = {}
    for topic, _t, data in msgs:
        if topic in pubs:
            pubs[topic].publish(data)
            sent.setdefault(topic, []).append(data)
            if pause:
                time.sleep(pause)
    return sent


def stop(proc, sig=signal.SIGINT, timeout=30):
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def received(bag) -> dict[str, list[bytes]]:
    from sep_control.bags.storage import read_raw

    raw = read_raw(bag)
    got: dict[str, list[bytes]] = {}
    for cid, data in zip(raw.conn_ids.tolist(), raw.data):
        got.setdefault(raw.connections[cid].topic, []).append(data)
    return got, raw


def same_payload(got: list[bytes], sent: list[bytes]) -> bool:
    """Equal CDR payloads. The middleware pads a serialized message to a multiple of 4 bytes
    and records the padding in the encapsulation options (bytes 2-3), so the bytes a
    subscriber (rosbag2 as well as this recorder) receives may end in up to 3 zero bytes more."""
    if len(got) != len(sent):
        return False
    for g, s in zip(got, sent):
        pad = len(g) - len(s)
        if g[:2] != s[:2] or g[4:len(s)] != s[4:] or not 0 <= pad < 4 or any(g[len(s):]):
            return False
    return True


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_record_bytes_roundtrip_and_independent_readers(tmp_path, ros, procs, storage):
    ep = synthetic_episode(small_scenario(n_steps=10, band_window=(5, 10), lqr_k_switch=4))
    msgs = episode_messages(ep)
    pubs = make_publishers(ros, TYPES)
    # the latched scenario is published before the recorder exists (transient_local)
    publish_all(pubs, [m for m in msgs if m[0] == "/sep/scenario"])
    bag = tmp_path / "bag"
    proc = start_recorder(bag, "--storage", storage, "--no-stop-at-end")
    procs.append(proc)
    wait_matched(pubs, proc)
    time.sleep(0.3)
    sent = publish_all(pubs, [m for m in msgs if m[0] != "/sep/scenario"])
    sent["/sep/scenario"] = [m[2] for m in msgs if m[0] == "/sep/scenario"]
    time.sleep(1.0)
    rc, out, err = stop(proc)
    assert rc == 0, err
    assert "SIGINT" in out and (bag / "metadata.yaml").is_file()
    got, raw = received(bag)
    assert raw.complete and raw.storage == storage
    assert set(got) == set(sent)
    for topic in sent:
        assert same_payload(got[topic], sent[topic]), topic
    # log times are receive times (ns, system clock), non-decreasing per topic
    now = time.time_ns()
    assert np.all((raw.log_times > now - 120e9) & (raw.log_times <= now))

    # independent reader 1: rosbags AnyReader, messages decode as the contract types
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {t: TYPES[t] for t in sent}
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
        assert qos["/sep/scenario"] and qos["/sep/scenario"][0].durability.name == "TRANSIENT_LOCAL"
        assert qos["/sep/measurements"][0].reliability.name == "RELIABLE"
        n = 0
        for conn, _t, rawdata in reader.messages():
            msg = reader.deserialize(rawdata, conn.msgtype)
            n += 1
            if conn.topic == "/sep/measurements":
                assert tuple(msg.name) == ep.info.output_names and msg.header.frame_id == "sep"
            if conn.topic == "/sep/field":
                assert msg.width == ep.info.n_field and msg.point_step == 40
        assert n == sum(len(v) for v in sent.values())

    if storage == "mcap":
        # independent reader 2: the mcap library; decode with rclpy's own deserializer
        from mcap.reader import make_reader
        from rclpy.serialization import deserialize_message

        mcap_file = next(bag.glob("*.mcap"))
        with open(mcap_file, "rb") as fh:
            reader = make_reader(fh)
            summary = reader.get_summary()
            assert summary is not None and summary.statistics.message_count == n
            count = 0
            for schema, channel, message in reader.iter_messages():
                assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
                assert schema.name == TYPES[channel.topic]
                msg = deserialize_message(message.data, _msg_class(schema.name))
                if channel.topic == "/sep/command":
                    assert msg.header.frame_id == "sep" and len(msg.effort) == ep.info.n_u
                count += 1
            assert count == n


def test_record_real_messages_and_stop_at_end(tmp_path, ros, procs):
    """Real rclpy message objects in, equal messages out (rclpy's serializer leaves alignment
    padding uninitialized, so bytes are compared after decoding); the recorder stops by itself after
    the plant's final measurement (step N of the recorded scenario)."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    from sep_plant.scenario import scenario_payload

    s = small_scenario(n_steps=6, band_window=(3, 6), lqr_k_switch=2)
    info, N = s.info, s.problem.n_steps
    pubs = make_publishers(ros, ["/sep/scenario", "/sep/measurements", "/sep/command"])
    bag = tmp_path / "bag"
    proc = start_recorder(bag, "--final-grace", "0.5")
    procs.append(proc)
    wait_matched(pubs, proc)
    pubs["/sep/scenario"].publish(String(data=scenario_payload(s, info)))
    time.sleep(0.3)
    sent = {"/sep/measurements": [], "/sep/command": []}
    dt_ns = T.dt_ns(info.dt)
    for k in range(N + 1):
        stamp = Time(sec=k * dt_ns // 10**9, nanosec=k * dt_ns % 10**9)
        m = JointState(name=list(info.output_names), position=[150.0 + k + j for j in range(info.n_y)])
        m.header.stamp, m.header.frame_id = stamp, "sep"
        pubs["/sep/measurements"].publish(m)
        sent["/sep/measurements"].append(m)
        if k < N:
            c = JointState(name=list(info.input_names), effort=[0.1 * k] * info.n_u)
            c.header.stamp, c.header.frame_id = stamp, "sep"
            pubs["/sep/command"].publish(c)
            sent["/sep/command"].append(c)
        time.sleep(0.01)
    out, err = proc.communicate(timeout=30)   # no signal: it must stop by itself
    assert proc.returncode == 0, err
    assert "episode ended" in out
    got, raw = received(bag)
    assert raw.complete
    for topic in sent:
        assert [deserialize_message(d, JointState) for d in got[topic]] == sent[topic]
    from sep_control.bags.reader import read_episode

    e = read_episode(bag)
    assert e.scenario == s and e.info == info
    np.testing.assert_array_equal(e.y[:, 0], 150.0 + np.arange(N + 1))
    assert "/sep/field" in e.missing and "/sep/field_image" not in e.missing


def test_record_sigkill_leaves_readable_bag(tmp_path, ros, procs):
    from sep_control.bags.reader import read_episode
    from sep_control.bags.storage import BagError

    ep = synthetic_episode(small_scenario(n_steps=30, band_window=(20, 30), lqr_k_switch=10))
    msgs = episode_messages(ep)
    pubs = make_publishers(ros, TYPES)
    publish_all(pubs, [m for m in msgs if m[0] == "/sep/scenario"])
    bag = tmp_path / "bag"
    proc = start_recorder(bag, "--no-stop-at-end", "--flush-interval", "0.05")
    procs.append(proc)
    wait_matched(pubs, proc)
    time.sleep(0.3)
    # the first 15 steps, then wait for a flush, then crash
    cut = next(i for i, m in enumerate(msgs) if m[0] == "/clock" and m is not msgs[0] and
               int.from_bytes(m[2][4:8], "little") * 10**9 + int.from_bytes(m[2][8:12], "little")
               >= 15 * T.dt_ns(ep.info.dt))
    sent = publish_all(pubs, [m for m in msgs[:cut] if m[0] != "/sep/scenario"])
    time.sleep(1.0)
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    assert not (bag / "metadata.yaml").exists()
    with pytest.raises(BagError, match=r"truncated.*messages recovered"):
        read_episode(bag)
    e = read_episode(bag, allow_truncated=True)
    assert not e.complete
    assert e.steps_with("measurements").tolist() == list(range(15))
    np.testing.assert_array_equal(e.F[:15], ep.F[:15])
    got, _raw = received(bag)
    for topic in sent:
        assert same_payload(got[topic], sent[topic])
    # repair: a complete bag that rosbags' AnyReader opens
    from sep_control.bags.repair import repair_bag

    fixed = repair_bag(bag, tmp_path / "fixed")
    from rosbags.highlevel import AnyReader

    with AnyReader([fixed]) as reader:
        assert sum(1 for _ in reader.messages()) == sum(len(v) for v in got.values())


def test_ready_file_skips_optional_topics_without_publisher(tmp_path, ros, procs):
    """The slab publishes no images: --ready-file waits for every required topic, not for them."""
    required = [t for t in TYPES if T.key_of(t) not in T.OPTIONAL]
    bag, ready = tmp_path / "bag", tmp_path / "ready"
    proc = start_recorder(bag, "--no-stop-at-end", "--ready-file", str(ready))
    procs.append(proc)
    time.sleep(1.0)
    assert not ready.exists()                       # no publisher of a required topic yet
    pubs = make_publishers(ros, required)
    wait_matched(pubs, proc)
    t0 = time.monotonic()
    while not ready.exists():
        assert time.monotonic() - t0 < 30 and proc.poll() is None, "ready file not written"
        time.sleep(0.05)
    rc, out, err = stop(proc)
    assert rc == 0, err


def test_record_cli_errors(tmp_path):
    env = dict(os.environ, PYTHONPATH=SRC)
    (tmp_path / "exists").mkdir()
    p = subprocess.run([sys.executable, "-m", "sep_control.ros.record_node", "--out", str(tmp_path / "exists")],
                       env=env, capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "exists already" in p.stderr and "Traceback" not in p.stderr
    p = subprocess.run([sys.executable, "-m", "sep_control.ros.record_node", "--help"], env=env,
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0 and "--storage" in p.stdout and "--stop-after-idle" in p.stdout
