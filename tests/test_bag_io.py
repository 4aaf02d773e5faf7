"""bag_io: synthetic contract bags (rosbags Writer, Jazzy typestore) read back exactly; bad bags."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from bag_synth import LAT_CMD_NS, T0_NS, small_scenario, synthetic_episode, write_bag
from sep_control.bag_io import BagError, read_episode, read_raw, repair_bag


@pytest.fixture(scope="module")
def ep():
    return synthetic_episode(small_scenario(), seed=3)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_roundtrip_exact(tmp_path, ep, storage):
    bag = write_bag(tmp_path / "bag", ep, storage=storage)
    e = read_episode(bag)
    s = ep.scenario
    assert e.scenario == s and e.scenario_source == "bag" and e.complete and not e.missing
    assert e.n_steps == s.n_steps and e.dt == s.dt
    for name in ("T", "T_hat", "T_std", "y", "u_cmd", "u"):
        np.testing.assert_array_equal(getattr(e, name), getattr(ep, name), err_msg=name)
    for k, a in enumerate(ep.a_hat):
        assert e.a_dim[k] == len(a)
        np.testing.assert_array_equal(e.a_hat[k, :len(a)], a)
        assert np.all(np.isnan(e.a_hat[k, len(a):]))
    np.testing.assert_array_equal(e.x, s.grid())
    assert e.diag_totals == ep.diag
    assert e.diagnostics["plant"]["step"] == str(s.n_steps)
    lat = e.step_recv_ns["heat_command"][:-1] - e.step_recv_ns["measurements"][:-1]
    assert np.all(lat == LAT_CMD_NS)
    tt = e.times["measurements"]
    dt_ns = int(round(s.dt * 1e9))
    np.testing.assert_array_equal(tt.stamp_ns, np.arange(s.n_steps + 1) * dt_ns)
    np.testing.assert_array_equal(tt.recv_ns, T0_NS + np.arange(s.n_steps + 1) * dt_ns)


def test_lone_mcap_file_and_missing_metadata(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep)
    mcap = next(bag.glob("*.mcap"))
    e1 = read_episode(mcap)
    (bag / "metadata.yaml").unlink()
    e2 = read_episode(bag)
    np.testing.assert_array_equal(e1.T, ep.T)
    np.testing.assert_array_equal(e2.T, ep.T)
    assert any("metadata.yaml missing" in n for n in e2.notes)


def test_missing_topics_are_listed_not_raised(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep, skip=("/slab/field_estimate", "/diagnostics", "/slab/heat_applied"))
    e = read_episode(bag)
    assert e.missing == ["/slab/heat_applied", "/slab/field_estimate", "/diagnostics"]
    assert np.all(np.isnan(e.T_hat)) and np.all(np.isnan(e.u))
    assert e.diag_totals == {}
    np.testing.assert_array_equal(e.T, ep.T)


def test_missing_scenario_uses_argument_or_infers(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep, skip=("/slab/scenario",))
    e = read_episode(bag, scenario=ep.scenario)
    assert e.scenario_source == "argument" and "/slab/scenario" in e.missing
    np.testing.assert_array_equal(e.T, ep.T)
    e = read_episode(bag)
    assert e.scenario is None and e.scenario_source == "inferred"
    assert e.dt == ep.scenario.dt and e.n_steps == ep.scenario.n_steps
    np.testing.assert_array_equal(e.T, ep.T)


def test_unknown_extra_topics_ignored(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep, extra_topics=True)
    e = read_episode(bag)
    assert e.ignored_topics == ["/rosout_like/extra", "/slab/unknown"]
    assert not e.missing
    np.testing.assert_array_equal(e.T, ep.T)


def test_truncated_mcap_recovers_prefix(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep)
    mcap = next(bag.glob("*.mcap"))
    full = read_raw(bag)
    data = mcap.read_bytes()
    # a bag cut in the middle of its data (crash): keep 60 %
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "cut.mcap").write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(BagError) as exc:
        read_episode(cut)
    msg = str(exc.value)
    assert "cut.mcap" in msg or str(cut) in msg
    assert "truncated" in msg and "messages recovered" in msg and "--allow-truncated" in msg
    raw = read_raw(cut)
    assert not raw.complete and 0 <= len(raw) <= len(full)
    assert raw.data == full.data[: len(raw)]          # an exact prefix, nothing half-read
    np.testing.assert_array_equal(raw.log_times, full.log_times[: len(raw)])


def test_truncated_small_chunks_recover_up_to_last_chunk(tmp_path, ep):
    """With the recorder's periodic chunk flushes, a cut loses at most the last chunk."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from bag_synth import TS, TYPES, _qos, episode_messages

    bag = tmp_path / "bag"
    msgs = episode_messages(ep)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for i, (topic, t, d) in enumerate(msgs):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, TYPES[topic], typestore=TS, offered_qos_profiles=[_qos()])
            w.write(conns[topic], t, d)
            if topic == "/slab/heat_applied":       # one chunk per step, as the recorder's flushes
                w.storage.close_chunk()
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    for frac in (0.3, 0.77, 0.999):
        cut = tmp_path / f"cut{frac}"
        cut.mkdir()
        (cut / "x.mcap").write_bytes(data[: int(len(data) * frac)])
        e = read_episode(cut, allow_truncated=True)
        ks = e.steps_with("heat_applied")
        assert ks.size >= int(frac * ep.scenario.n_steps) - 2
        np.testing.assert_array_equal(e.T[: ks[-1] + 1], ep.T[: ks[-1] + 1])
        assert not e.complete
    fixed = repair_bag(tmp_path / "cut0.77", tmp_path / "fixed")
    e = read_episode(fixed)
    assert e.complete and e.steps_with("heat_applied").size >= int(0.77 * ep.scenario.n_steps) - 2


@pytest.mark.parametrize("damage", ["magic", "garbage_middle", "empty", "not_a_bag", "sqlite_garbage"])
def test_corrupt_bags_raise_bagerror(tmp_path, ep, damage):
    if damage == "sqlite_garbage":
        bag = write_bag(tmp_path / "bag", ep, storage="sqlite3")
        db = next(bag.glob("*.db3"))
        db.write_bytes(b"this is not sqlite" * 100)
    else:
        bag = write_bag(tmp_path / "bag", ep)
        mcap = next(bag.glob("*.mcap"))
        data = bytearray(mcap.read_bytes())
        if damage == "magic":
            data[:8] = b"NOTMCAP!"
        elif damage == "garbage_middle":          # a record header in the data section destroyed
            first_chunk = data.index(b"\x06", 8 + 9 + 4)
            data[first_chunk:first_chunk + 64] = b"\x7f" * 64
        elif damage == "empty":
            data = bytearray()
        elif damage == "not_a_bag":
            shutil.rmtree(bag)
            bag.mkdir()
            (bag / "notes.txt").write_text("hello")
        if damage != "not_a_bag":
            mcap.write_bytes(bytes(data))
    with pytest.raises(BagError) as exc:
        read_episode(bag, allow_truncated=True)
    assert str(bag) in str(exc.value)


def test_nonexistent(tmp_path):
    with pytest.raises(BagError, match="no such bag"):
        read_episode(tmp_path / "nope")


def test_undecodable_message_is_skipped_and_noted(tmp_path, ep):
    from rosbags.rosbag2 import StoragePlugin, Writer

    from bag_synth import TS, TYPES, _qos, episode_messages

    bag = tmp_path / "bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        for topic, t, d in episode_messages(ep):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, TYPES[topic], typestore=TS, offered_qos_profiles=[_qos()])
            if topic == "/slab/heat_command" and d[4:8] == (5).to_bytes(4, "little") and d[8:12] == bytes(4):
                d = d[:30]                          # step 5 s: cut payload
            w.write(conns[topic], t, d)
    e = read_episode(bag)
    assert any("undecodable" in n for n in e.notes)
    assert np.isnan(e.u_cmd[20]).all()
    assert np.isfinite(e.u_cmd).sum() == (ep.scenario.n_steps - 1) * ep.scenario.n_u
