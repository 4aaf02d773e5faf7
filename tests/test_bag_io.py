"""Bag reading and writing (`sep_control.bags`: storage, episode, repair, writer): synthetic contract
bags (rosbags Writer, Jazzy typestore) read back exactly, for the slab, sep 0.1 slab bags (both
namings) and a 2-D grid plant; the one stamp tolerance; bad bags; the recorder's ROS-free sink;
the real sep 0.1 bag."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bag_synth import (LAT_CMD_NS, NAMINGS, T0_NS, TYPES, episode_messages, grid_episode, legacy_episode,
                       small_scenario, synthetic_episode, topic_namer, write_bag, write_messages)
from sep_control.bags.reader import read_episode
from sep_control.bags.repair import repair_bag
from sep_control.bags.storage import BagError, read_raw
from sep_plant import topics as T


@pytest.fixture(scope="module")
def ep():
    return synthetic_episode(small_scenario(), seed=3)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_roundtrip_exact(tmp_path, ep, storage):
    bag = write_bag(tmp_path / "bag", ep, storage=storage)
    e = read_episode(bag)
    s, N = ep.scenario, ep.scenario.problem.n_steps
    assert e.scenario == s and e.info == ep.info and e.scenario_source == "bag" and e.complete and not e.missing
    assert e.n_steps == N and e.dt == ep.info.dt
    for name in ("F", "F_hat", "F_std", "y", "u_cmd", "u"):
        np.testing.assert_array_equal(getattr(e, name), getattr(ep, name), err_msg=name)
    for k, a in enumerate(ep.a_hat):
        assert e.a_dim[k] == len(a)
        np.testing.assert_array_equal(e.a_hat[k, :len(a)], a)
        assert np.all(np.isnan(e.a_hat[k, len(a):]))
    np.testing.assert_array_equal(e.xyz, ep.xyz)
    assert e.field_name == "temperature" and e.images == {}
    assert e.diag_totals == ep.diag
    assert e.diagnostics["plant"]["step"] == str(N)
    lat = e.step_recv_ns["command"][:-1] - e.step_recv_ns["measurements"][:-1]
    assert np.all(lat == LAT_CMD_NS)
    tt = e.times["measurements"]
    dt_ns = T.dt_ns(ep.info.dt)
    np.testing.assert_array_equal(tt.stamp_ns, np.arange(N + 1) * dt_ns)
    np.testing.assert_array_equal(tt.recv_ns, T0_NS + np.arange(N + 1) * dt_ns)
    assert e.counts["/clock"] == N + 1 and e.counts[T.FIELD_IMAGE] == 0


def test_old_sep01_bag_flat_scenario(tmp_path):
    """A sep 0.1 bag: the plant published the flat slab scenario JSON alone; the reader builds the
    built-in slab for its description and gets the same scenario as the new format."""
    old = legacy_episode(small_scenario(), seed=5)
    assert '"k_band"' in old.payload and '"plant"' not in old.payload
    e = read_episode(write_bag(tmp_path / "old", old))
    assert e.scenario_source == "bag" and e.scenario == old.scenario and e.info == old.info
    assert not e.scenario.plant_mismatches(small_scenario())
    assert e.field_name == "temperature" and not e.missing
    np.testing.assert_array_equal(e.F, old.F)
    np.testing.assert_array_equal(e.F_hat, old.F_hat)
    np.testing.assert_array_equal(e.u, old.u)


EPISODE_ARRAYS = ("F", "F_hat", "F_std", "y", "u_cmd", "u", "a_hat", "a_dim", "xyz")


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_both_namings_read_as_the_same_episode(tmp_path, ep, storage):
    """The same episode written with the contract's names (sep, command, applied_input) and with
    sep 0.1's (slab, heat_command, heat_applied) reads as the same Episode: the namespace is
    detected, the old names map through `topics.LEGACY_TOPICS`, nothing is missing or ignored."""
    eps = {n: read_episode(write_bag(tmp_path / n, ep, storage=storage, naming=n)) for n in NAMINGS}
    old_topics = {c.topic for c in read_raw(tmp_path / "sep01").connections.values()}
    assert {"/slab/heat_command", "/slab/heat_applied", "/slab/measurements"} <= old_topics
    assert not any(t.startswith("/sep/") or t.endswith(("/command", "/applied_input")) for t in old_topics)
    new, old = eps["current"], eps["sep01"]
    for e in (new, old):
        assert e.scenario == ep.scenario and e.complete and not e.missing and not e.ignored_topics and not e.notes
    for name in EPISODE_ARRAYS:
        np.testing.assert_array_equal(getattr(old, name), getattr(new, name), err_msg=name)
    np.testing.assert_array_equal(old.u, ep.u)
    assert old.counts == new.counts and old.counts[T.COMMAND] == ep.scenario.problem.n_steps
    assert old.diag_totals == new.diag_totals and old.diagnostics == new.diagnostics
    assert old.step_recv_ns.keys() == new.step_recv_ns.keys()
    for key in new.step_recv_ns:
        np.testing.assert_array_equal(old.step_recv_ns[key], new.step_recv_ns[key], err_msg=key)
    # the namespace given explicitly reads the same
    e = read_episode(tmp_path / "sep01", namespace="slab")
    np.testing.assert_array_equal(e.u_cmd, new.u_cmd)


@pytest.mark.parametrize("shape", [(6, 5), (4, 3, 3)])
def test_grid_plant_bag_with_images(tmp_path, shape):
    """A 2-D / 3-D grid plant whose field is called phi, with the 32FC1 image topics."""
    gep = grid_episode(shape, seed=1)
    e = read_episode(write_bag(tmp_path / "grid", gep))
    N = gep.scenario.problem.n_steps
    assert e.info.grid_shape == shape and e.field_name == "phi" and e.scenario == gep.scenario
    assert not e.missing and not e.notes, e.notes
    np.testing.assert_array_equal(e.F, gep.F)
    np.testing.assert_array_equal(e.F_std, gep.F_std)
    np.testing.assert_array_equal(e.xyz, gep.xyz)
    assert set(e.images) == {T.FIELD_IMAGE, T.FIELD_ESTIMATE_IMAGE}
    assert sorted(e.images[T.FIELD_IMAGE]) == list(range(N + 1))
    img = e.images[T.FIELD_ESTIMATE_IMAGE][7]
    assert img.dtype == np.float32 and img.shape == shape[:2]
    np.testing.assert_array_equal(img, T.image_of_field(gep.F_hat[7], shape))
    assert e.steps_with(T.FIELD_IMAGE).size == N + 1


def test_images_are_optional_topics(tmp_path):
    gep = grid_episode(seed=2)
    e = read_episode(write_bag(tmp_path / "noimg", gep, skip=(T.topic_name(T.FIELD_IMAGE),
                                                               T.topic_name(T.FIELD_ESTIMATE_IMAGE))))
    assert not e.missing and e.images == {}


def test_one_stamp_tolerance(tmp_path, ep):
    """A stamp 0.05 % of dt off k dt is step k; 0.2 % off is off the grid and ignored (noted)."""
    step = T.dt_ns(ep.info.dt)
    shift = {(T.MEASUREMENTS, 5): step // 2000, (T.MEASUREMENTS, 6): -(step // 2000),
             (T.MEASUREMENTS, 7): step // 500, (T.FIELD, 9): -(step // 500)}
    e = read_episode(write_bag(tmp_path / "bag", ep, stamp_shift_ns=shift))
    np.testing.assert_array_equal(e.y[5], ep.y[5])
    np.testing.assert_array_equal(e.y[6], ep.y[6])
    assert np.all(np.isnan(e.y[7])) and np.all(np.isnan(e.F[9]))
    np.testing.assert_array_equal(e.F[8], ep.F[8])
    assert 7 not in e.steps_with("measurements") and 5 in e.steps_with("measurements")
    assert any("2 messages with stamps off the step grid" in n for n in e.notes), e.notes
    # the same tolerance as every node (sep_plant.topics)
    assert T.step_of_stamp(7 * step + step // 2000, step) == 7 and T.step_of_stamp(7 * step + step // 500, step) is None


def test_cloud_with_bad_layout_is_skipped(tmp_path, ep):
    """A cloud whose std channel is not <field>_std is refused (noted), the rest is read."""
    from bag_synth import TS

    msgs = episode_messages(ep)
    i = next(j for j, m in enumerate(msgs) if m[0] == T.topic_name(T.FIELD) and j > 20)
    msg = TS.deserialize_cdr(msgs[i][2], T.POINT_CLOUD2)
    msg.fields[4].name = "sigma"
    msgs[i] = (msgs[i][0], msgs[i][1], bytes(TS.serialize_cdr(msg, T.POINT_CLOUD2)))
    e = read_episode(write_messages(tmp_path / "bag", msgs))
    k = int(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) // T.dt_ns(ep.info.dt)
    assert np.all(np.isnan(e.F[k])) and np.isfinite(e.F[k + 1]).all()
    assert any("malformed" in n and "<field>_std" in n for n in e.notes), e.notes


def test_lone_mcap_file_and_missing_metadata(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep)
    mcap = next(bag.glob("*.mcap"))
    e1 = read_episode(mcap)
    (bag / "metadata.yaml").unlink()
    e2 = read_episode(bag)
    np.testing.assert_array_equal(e1.F, ep.F)
    np.testing.assert_array_equal(e2.F, ep.F)
    assert any("metadata.yaml missing" in n for n in e2.notes)


def test_missing_topics_are_listed_not_raised(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep, skip=("/sep/field_estimate", "/diagnostics", "/sep/applied_input"))
    e = read_episode(bag)
    assert e.missing == ["/sep/applied_input", "/sep/field_estimate", "/diagnostics"]
    assert np.all(np.isnan(e.F_hat)) and np.all(np.isnan(e.u))
    assert e.diag_totals == {}
    np.testing.assert_array_equal(e.F, ep.F)


def test_missing_scenario_uses_argument_or_infers(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep, skip=("/sep/scenario",))
    e = read_episode(bag, scenario=ep.scenario, info=ep.info)
    assert e.scenario_source == "argument" and "/sep/scenario" in e.missing and e.info == ep.info
    np.testing.assert_array_equal(e.F, ep.F)
    e = read_episode(bag, scenario=ep.scenario)                 # the description from the scenario's plant
    assert e.scenario_source == "argument" and e.info == ep.info
    e = read_episode(bag)
    assert e.scenario is None and e.info is None and e.scenario_source == "inferred"
    assert e.dt == ep.info.dt and e.n_steps == ep.scenario.problem.n_steps
    np.testing.assert_array_equal(e.F, ep.F)
    np.testing.assert_array_equal(e.u, ep.u)
    np.testing.assert_array_equal(e.xyz, ep.xyz)


def test_unknown_extra_topics_ignored(tmp_path, ep):
    bag = write_bag(tmp_path / "bag", ep, extra_topics=True)
    e = read_episode(bag)
    assert e.ignored_topics == ["/rosout_like/extra", "/sep/unknown"]
    assert not e.missing
    np.testing.assert_array_equal(e.F, ep.F)


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
    bag = write_bag(tmp_path / "bag", ep, chunk_per_step=True)   # one chunk per step, as the recorder's flushes
    mcap = next(bag.glob("*.mcap"))
    data = mcap.read_bytes()
    for frac in (0.3, 0.77, 0.999):
        cut = tmp_path / f"cut{frac}"
        cut.mkdir()
        (cut / "x.mcap").write_bytes(data[: int(len(data) * frac)])
        e = read_episode(cut, allow_truncated=True)
        ks = e.steps_with("applied_input")
        assert ks.size >= int(frac * ep.scenario.problem.n_steps) - 2
        np.testing.assert_array_equal(e.F[: ks[-1] + 1], ep.F[: ks[-1] + 1])
        assert not e.complete
    fixed = repair_bag(tmp_path / "cut0.77", tmp_path / "fixed")
    e = read_episode(fixed)
    assert e.complete and e.steps_with("applied_input").size >= int(0.77 * ep.scenario.problem.n_steps) - 2


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
    msgs = []
    for topic, t, d in episode_messages(ep):
        if topic == "/sep/command" and d[4:8] == (5).to_bytes(4, "little") and d[8:12] == bytes(4):
            d = d[:30]                          # step 5 s: cut payload
        msgs.append((topic, t, d))
    e = read_episode(write_messages(tmp_path / "bag", msgs))
    assert any("undecodable" in n for n in e.notes)
    assert np.isnan(e.u_cmd[20]).all()
    assert np.isfinite(e.u_cmd).sum() == (ep.scenario.problem.n_steps - 1) * ep.info.n_u


def _sink(out, **kw):
    from sep_control.bags.writer import BagSink

    sink = BagSink(out, **kw)
    sink.types.update(TYPES)
    return sink


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bag_sink_writes_exactly_what_it_is_fed(tmp_path, ep, storage):
    """The recorder's writer (no ROS): the queued bytes and log times make a complete bag that reads
    as the episode; it notices the final step (measurement N of the scenario's N)."""
    msgs = episode_messages(ep)
    sink = _sink(tmp_path / "bag", storage=storage)
    sink.start()
    for topic, t, data in msgs:
        sink.put(topic, t, data)
    sink.close()
    assert sink.error is None and sink.total == len(msgs)
    assert sink.n_steps == ep.scenario.problem.n_steps and sink.final_seen is not None
    raw = read_raw(tmp_path / "bag")
    assert raw.complete and raw.has_metadata and raw.storage == storage
    assert raw.data == [d for _, _, d in msgs]
    np.testing.assert_array_equal(raw.log_times, [t for _, t, _ in msgs])
    e = read_episode(tmp_path / "bag")
    assert not e.missing and not e.notes
    for name in ("F", "F_hat", "F_std", "y", "u_cmd", "u"):
        np.testing.assert_array_equal(getattr(e, name), getattr(ep, name), err_msg=name)


def test_bag_sink_flushes_while_open(tmp_path, ep):
    """What the sink wrote is readable from the open file (as after a SIGKILL) once it flushed."""
    import time

    msgs = episode_messages(ep)
    half = len(msgs) // 2
    sink = _sink(tmp_path / "bag", flush_interval=0.01)
    sink.start()
    for topic, t, data in msgs[:half]:
        sink.put(topic, t, data)
    mcap = next((tmp_path / "bag").glob("*.mcap"))
    cut = tmp_path / "cut"
    cut.mkdir()
    t0 = time.monotonic()
    n = 0
    while n < half and time.monotonic() - t0 < 20:   # until the writer thread flushed all of them
        time.sleep(0.05)
        (cut / "cut.mcap").write_bytes(mcap.read_bytes())
        try:
            n = len(read_raw(cut))
        except BagError:            # nothing flushed yet (empty file, or a part of the header)
            n = 0
    raw = read_raw(cut)
    sink.close()
    assert not raw.complete and raw.data == [d for _, _, d in msgs[:half]]
    assert read_raw(tmp_path / "bag").complete


def test_bag_sink_close_reports_a_writer_that_did_not_finish(tmp_path, ep):
    """0.8.0's close() joined with a timeout and never looked: a stuck writer went unnoticed and the
    recorder reported a clean stop with a bag that had no summary."""
    import threading

    release = threading.Event()
    sink = _sink(tmp_path / "bag")
    real = sink._write
    sink._write = lambda *a: (release.wait(30), real(*a))   # the writer thread stalls on a message
    sink.start()
    topic, t, data = episode_messages(ep)[0]
    sink.put(topic, t, data)
    assert sink.close(timeout=0.2) is False
    assert isinstance(sink.error, TimeoutError) and "did not finish" in str(sink.error)
    release.set()
    assert sink.close(timeout=30) is True and read_raw(tmp_path / "bag").complete


def test_bag_sink_counts_under_its_lock(tmp_path, ep):
    """The writer thread updates `counts` under `sink.lock`, which the recorder's readers (`total`,
    `counted()`) take too: 0.8.0 read them from another thread with no lock."""
    import time

    msgs = episode_messages(ep)[:3]
    sink = _sink(tmp_path / "bag")
    sink.start()
    with sink.lock:
        for topic, t, data in msgs:
            sink.put(topic, t, data)
        time.sleep(0.3)                      # the writer thread has the messages, waits for the lock
        assert sum(sink.counts.values()) <= 1
    assert sink.close() is True
    assert sink.total == 3 and sum(sink.counted().values()) == 3


def test_recorder_closes_its_bag_before_its_node_goes(tmp_path, monkeypatch):
    """0.8.0 destroyed the node first: the writer thread, still draining, asked the dead node for the
    QoS of a topic's first message and lost it silently."""
    pytest.importorskip("rclpy")
    from sep_control.bags import writer
    from sep_control.ros import record_node

    events = []
    real_close, real_destroy = writer.BagSink.close, record_node.Recorder.destroy_node
    monkeypatch.setattr(writer.BagSink, "close", lambda self, *a, **k: (events.append("sink closed"),
                                                                        real_close(self, *a, **k))[1])
    monkeypatch.setattr(record_node.Recorder, "destroy_node",
                        lambda self: (events.append("node destroyed"), real_destroy(self))[1])
    monkeypatch.setattr(record_node, "_record", lambda node, args, stop: "test stop")
    monkeypatch.setattr(record_node.signal, "signal", lambda *a: None)   # keep pytest's handlers
    assert record_node.main(["--out", str(tmp_path / "bag")]) == 0
    assert events == ["sink closed", "node destroyed"]


def test_bag_sink_refuses_an_existing_directory(tmp_path):
    (tmp_path / "bag").mkdir()
    sink = _sink(tmp_path / "bag")
    with pytest.raises(Exception, match="exists"):
        sink.start()
    sink.close()


DATA = Path(__file__).resolve().parent / "data"
SEP01_BAG = DATA / "bag_sep01"            # recorded by sep 0.1's demo (commit 488f89e), see data/README.txt


def test_real_sep01_bag_read_and_analysed():
    """A REAL bag written by sep 0.1's demo (plant + lqg + record, slab n_x 20, N 40, seed 7 run 2):
    read with today's API with and without sep 0.1's design file (format v1); the recorded
    field/inputs/measurements are the old plant's trajectory file exactly, and today's metrics are
    those sep 0.1's own `analyze` and `demo` wrote for this bag."""
    from sep_control.evaluation import metrics as M
    from sep_control.bags.analysis import analyze
    from sep_estimator.design_file import load_design
    from sep_plant.scenario import load_scenario

    traj = np.load(DATA / "bag_sep01_trajectory.npz", allow_pickle=False)
    old_scenario = json.loads(bytes(traj["scenario"]).decode())
    assert '"plant"' not in bytes(traj["scenario"]).decode() and old_scenario["k_band"] == 24
    assert (int(traj["seed"]), int(traj["run"])) == (7, 2)
    old_analyze = json.loads((DATA / "bag_sep01_analyze_metrics.json").read_text())[0]
    old_demo = json.loads((DATA / "bag_sep01_demo_metrics.json").read_text())
    scen_file = load_scenario(DATA / "bag_sep01_scenario.yaml")

    # -- sep 0.1's topic names are those bag_synth writes with naming="sep01"
    topics = {c.topic for c in read_raw(SEP01_BAG).connections.values()}
    assert topics == {topic_namer("sep01")(t.name) for t in T.TOPICS if t.name not in T.OPTIONAL}

    # -- read_episode, scenario from the bag's flat sep 0.1 payload
    e = read_episode(SEP01_BAG)
    s = e.scenario
    assert e.scenario_source == "bag" and s.plant_type == "slab" and s == scen_file
    assert s.plant_config["n_x"] == 20 and s.problem.window == (24, 40) and s.problem.k_switch == 19
    assert e.n_steps == 40 and e.dt == 0.25 and (e.info.n_x, e.info.n_u, e.info.n_y, e.info.n_field) == (20, 5, 5, 20)
    assert e.field_name == "temperature" and e.info.grid_shape is None
    assert e.complete and not e.missing and not e.notes and not e.ignored_topics and e.images == {}
    assert {k: e.counts[k] for k in ("/clock", "measurements", "command", "applied_input", "state_estimate",
                                      "field_estimate", "field", "scenario")} == \
        {"/clock": 41, "measurements": 41, "command": 40, "applied_input": 40, "state_estimate": 41,
         "field_estimate": 41, "field": 41, "scenario": 1}
    np.testing.assert_array_equal(e.F, traj["T"])           # the old plant's true field, bit for bit
    np.testing.assert_array_equal(e.u, traj["U"])
    np.testing.assert_array_equal(e.u_cmd, traj["U"])
    np.testing.assert_array_equal(e.y, traj["Y"])
    np.testing.assert_array_equal(e.xyz[:, 0], s.plant.grid())
    assert np.isfinite(e.F_hat).all() and np.isfinite(e.F_std).all() and (e.F_std[1:] > 0).all()
    assert e.diag_totals == {"deadline_misses": 0, "rejected_messages": 0}

    # -- sep 0.1's design file (v1) for the same plant: no mismatch, the same episode
    design = load_design(DATA / "bag_sep01_design.npz")
    assert design.meta["upgraded_from_version"] == 1 and not design.scenario.plant_mismatches(s)
    e2 = read_episode(SEP01_BAG, scenario=design.scenario, info=design.info)
    assert e2.scenario_source == "bag" and e2.scenario == s
    np.testing.assert_array_equal(e2.F, e.F)

    # -- analyze: today's metrics = those sep 0.1 computed (its analyze of the bag, its demo's
    # trajectory metrics); mean_dev_62_5 (step min(250, N) = 40) is today's mean_dev_end, while
    # today's mean_dev_start is at the band window's first step (24), not at t = 37.5 s
    same = ("cost_mean", "cost_std", "in_band", "rms", "n_runs", "coverage_2sigma", "deadline_misses",
            "rejected_messages", "latency_p50_s", "latency_p99_s", "field_nees", "field_rmse", "latency_max_s",
            "latency_estimate_p50_s", "latency_estimate_p99_s", "episode_wall_s", "episode_sim_s",
            "steps_recorded", "complete")
    for dsg in (None, DATA / "bag_sep01_design.npz"):
        rep = analyze(SEP01_BAG, dsg)
        m = rep.metrics
        assert not rep.mismatch and not rep.notes, rep.notes
        for k in same:
            assert m[k] == pytest.approx(old_analyze[k], rel=1e-12, abs=0), (dsg, k)
        for k in ("cost_mean", "in_band", "rms", "coverage_2sigma"):
            assert m[k] == pytest.approx(old_demo[k], rel=1e-12, abs=0), (dsg, k)
        assert m["in_band"] == 1.0 and m["steps_recorded"] == 41 and m["complete"] is True
        if dsg is None:
            assert m["mean_dev_start"] is None and m["mean_dev_end"] is None
        else:
            assert m["mean_dev_end"] == pytest.approx(old_analyze["mean_dev_62_5"], rel=1e-12)
            assert m["mean_dev_end"] == pytest.approx(old_demo["mean_dev_62_5"], rel=1e-12)
            assert m["mean_dev_start"] == M.mean_deviation(traj["T"][None], design.nominal.field, 24)
