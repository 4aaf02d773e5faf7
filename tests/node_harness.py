"""Test harness for the node integration tests: node processes that are always cleaned up, and
an in-process probe node that records/publishes contract topics.

* `Launcher` starts the installed executables (colcon install of this checkout, resolved like
  `ros2 run`: <prefix>/lib/<pkg>/<exe>) in their own process group with the test session's
  isolated ROS_DOMAIN_ID and localhost discovery; `close()` (called by the `launcher` fixture's
  finalizer) interrupts, then kills every process group still alive.
* `Probe` is an rclpy node in its own Context, spun by a background thread: it records every
  contract topic by step, and can act as a fake plant or controller (publish measurements,
  applied inputs, commands, estimates, a latched scenario) for the fault tests.
"""
from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from ros_helpers import diagnostic_values, level_of, parse_field_cloud

EXECUTABLES = {'plant': 'sep_plant', 'estimator': 'sep_estimator', 'lqr': 'sep_control',
               'lqg': 'sep_control', 'demo': 'sep_control', 'record': 'sep_control'}


class NodeProcess:
    def __init__(self, name: str, argv: list[str], env: dict, log: Path):
        self.name, self.argv, self.log_path = name, argv, log
        self._fh = open(log, 'wb')
        self.popen = subprocess.Popen(argv, env=env, stdout=self._fh, stderr=subprocess.STDOUT,
                                      stdin=subprocess.DEVNULL, start_new_session=True)
        self.pgid = self.popen.pid  # start_new_session: the child leads its own group

    @property
    def returncode(self):
        return self.popen.poll()

    def wait(self, timeout: float) -> int:
        try:
            return self.popen.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(f'{self.name} still running after {timeout} s; output:\n'
                                 f'{self.output()}') from None

    def signal(self, sig: int) -> None:
        try:
            os.killpg(self.pgid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    def stop(self, grace: float = 5.0) -> None:
        """SIGINT, then SIGKILL after `grace` seconds; always reaps the process group."""
        if self.popen.poll() is None:
            self.signal(signal.SIGINT)
            try:
                self.popen.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                pass
        self.signal(signal.SIGKILL)  # stray children of the group, if any
        try:
            self.popen.wait(timeout=5)
        except subprocess.TimeoutExpired:
            pass
        self._fh.close()

    def output(self) -> str:
        if not self._fh.closed:
            self._fh.flush()
        try:
            return self.log_path.read_text(errors='replace')
        except OSError:
            return ''


class Launcher:
    def __init__(self, install, tmp_path: Path):
        self.install = install          # tests/conftest.ColconInstall
        self.tmp = tmp_path
        self.procs: list[NodeProcess] = []

    def path(self, exe: str) -> str:
        pkg = EXECUTABLES[exe]
        return str(self.install.prefix(pkg) / 'lib' / pkg / exe)

    def start(self, exe: str, *args: str, params: dict | None = None, name: str | None = None,
              env: dict | None = None) -> NodeProcess:
        argv = [self.path(exe), *args]
        if params:
            if '--ros-args' not in argv:
                argv.append('--ros-args')
            for k, v in params.items():
                if isinstance(v, bool):
                    v = str(v).lower()
                argv += ['-p', f'{k}:={v}']
        name = name or f'{exe}{len(self.procs)}'
        proc = NodeProcess(name, argv, {**self.install.env, **(env or {})},
                           self.tmp / f'{name}.log')
        self.procs.append(proc)
        return proc

    def close(self) -> None:
        for p in reversed(self.procs):
            p.stop(grace=3.0)

    def dump(self) -> str:
        return '\n'.join(f'--- {p.name} (rc {p.returncode}): {" ".join(p.argv)}\n{p.output()}'
                         for p in self.procs)


class Probe:
    """An in-process rclpy node (own Context, background spin thread)."""

    def __init__(self, namespace: str = 'sep', name: str = 'probe'):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions

        from sep_plant.ros import contract as c

        self.c = c
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node(name, namespace=namespace, context=self.ctx)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        self.msgs: dict[str, list] = defaultdict(list)      # topic -> [(recv_time, msg)]
        self.subs = {}
        self.pubs = {}
        self.hooks: dict[str, list] = defaultdict(list)   # topic -> [f(msg)] (in the spin thread)
        self._stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop and self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - shutting down
                if self._stop:
                    return
                raise

    # -------------------------------------------------------------- topics
    def subscribe(self, *topics: str) -> 'Probe':
        from diagnostic_msgs.msg import DiagnosticArray
        c = self.c
        for t in topics:
            from rclpy.qos import QoSProfile
            if t == c.DIAGNOSTICS:
                typ, qos = DiagnosticArray, c.DIAGNOSTICS_QOS
            else:
                typ, qos = c.TOPIC_TYPES[t], c.TOPIC_QOS[t]
            # a recorder must not lose samples while this (Python, GIL-sharing) thread lags
            qos = QoSProfile(history=qos.history, depth=max(qos.depth, 10000),
                             reliability=qos.reliability, durability=qos.durability)
            cb = (lambda topic: (lambda m: self._store(topic, m)))(t)
            self.subs[t] = self.node.create_subscription(typ, t, cb, qos)
        return self

    def _store(self, topic: str, msg) -> None:
        with self.lock:
            self.msgs[topic].append((time.perf_counter(), msg))
        for fn in self.hooks[topic]:
            fn(msg)

    def on(self, topic: str, fn) -> None:
        """Call fn(msg) for every message on a subscribed topic (in the spin thread)."""
        self.hooks[topic].append(fn)

    def count(self, t: str) -> int:
        with self.lock:
            return len(self.msgs[t])

    def publisher(self, t: str):
        from diagnostic_msgs.msg import DiagnosticArray
        c = self.c
        if t not in self.pubs:
            typ = DiagnosticArray if t == c.DIAGNOSTICS else c.TOPIC_TYPES[t]
            self.pubs[t] = self.node.create_publisher(typ, t, c.TOPIC_QOS[t])
        return self.pubs[t]

    def publish(self, t: str, msg) -> None:
        self.publisher(t).publish(msg)

    def received(self, t: str) -> list:
        with self.lock:
            return [m for _, m in self.msgs[t]]

    def by_step(self, t: str, dt: float) -> dict[int, object]:
        """Last message of each step on topic t."""
        out = {}
        for m in self.received(t):
            out[self.c.step_of_stamp(m.header.stamp, dt)] = m
        return out

    def wait_for(self, cond, timeout: float, what: str = 'condition'):
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            v = cond()
            if v:
                return v
            time.sleep(0.01)
        raise AssertionError(f'timed out after {timeout} s waiting for {what}')

    def wait_matched(self, timeout: float = 20.0, subs: tuple[str, ...] = (), pubs: tuple[str, ...] = ()):
        """Wait until the given subscriptions have a publisher and publishers a subscriber."""
        def ok():
            return (all(self.subs[t].get_publisher_count() > 0 for t in subs)
                    and all(self.pubs[t].get_subscription_count() > 0 for t in pubs))
        self.wait_for(ok, timeout, f'publishers on {subs} / subscribers on {pubs}')
        # Our side seeing the peer's endpoint does not mean the peer's writer has matched our
        # reader yet (discovery is asymmetric); a reliable, volatile sample written before that
        # is lost. 0.2 s lost estimate 0 once in a loaded CI run (sep 0.5); 0.5 s settles it.
        time.sleep(0.5)

    def diagnostics(self, name_part: str) -> list[dict]:
        """Key/values of every /diagnostics status whose name contains name_part."""
        out = []
        for arr in self.received(self.c.DIAGNOSTICS):
            for st in arr.status:
                if name_part in st.name:
                    d = diagnostic_values(st)
                    d['_level'] = level_of(st)
                    d['_message'] = st.message
                    out.append(d)
        return out

    def close(self) -> None:
        self._stop = True
        self.thread.join(timeout=5)
        try:
            self.executor.shutdown(timeout_sec=1)
            self.node.destroy_node()
        finally:
            if self.ctx.ok():
                self.ctx.try_shutdown()


def field_matrix(probe: Probe, topic: str, dt: float, n_steps: int, key: str = 'temperature', column: int | None = None):
    """(N+1, n_field) array of a field topic's channel `key` (or channel number `column`) by step
    (NaN rows for missing steps)."""
    msgs = probe.by_step(topic, dt)
    rows = []
    for k in range(n_steps + 1):
        m = msgs.get(k)
        if m is None:
            rows.append(None)
            continue
        channels = parse_field_cloud(m)
        rows.append(list(channels.values())[column] if column is not None else channels[key])
    n = max(len(r) for r in rows if r is not None)
    return np.array([r if r is not None else np.full(n, np.nan) for r in rows])


def joint_matrix(probe: Probe, topic: str, dt: float, steps: int, field: str):
    msgs = probe.by_step(topic, dt)
    rows = [np.asarray(getattr(msgs[k], field)) if k in msgs else None for k in range(steps)]
    n = max(len(r) for r in rows if r is not None)
    return np.array([r if r is not None else np.full(n, np.nan) for r in rows])


def wait_for_episode(probe: Probe, plant: NodeProcess, controllers: list[NodeProcess], case: Case) -> None:
    """Wait for a lockstep episode's end: the plant and the controllers exit 0, and every field,
    field estimate, applied input and measurement of the episode (k = 0..N) reached the probe."""
    from sep_plant.ros import contract as c

    assert plant.wait(120) == 0, plant.output()
    for p in controllers:
        assert p.wait(30) == 0, p.output()
    dt, N = case.dt, case.n_steps
    probe.wait_for(lambda: len(probe.by_step(c.FIELD, dt)) == N + 1, 10, 'all field messages')
    probe.wait_for(lambda: len(probe.by_step(c.FIELD_ESTIMATE, dt)) == N + 1, 10, 'all field estimates')
    probe.wait_for(lambda: len(probe.by_step(c.APPLIED_INPUT, dt)) == N, 10,
                   f'all applied_input (have {sorted(probe.by_step(c.APPLIED_INPUT, dt))})')
    probe.wait_for(lambda: len(probe.by_step(c.MEASUREMENTS, dt)) == N + 1, 10, 'all measurements')


# ------------------------------------------------------------------------------ fixtures
import pytest  # noqa: E402

SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=20)


class Case:
    """A scenario file and its design file."""

    def __init__(self, scenario, scenario_file: Path, design, design_file: Path):
        self.scenario, self.scenario_file = scenario, scenario_file
        self.design, self.design_file = design, design_file

    @property
    def plant(self):
        return self.scenario.plant

    @property
    def dt(self) -> float:
        return self.design.info.dt

    @property
    def n_steps(self) -> int:
        return self.design.n_steps


def make_case(root: Path, name: str, yaml_text: str | None = None, settings: dict | None = None,
              **flat_keys) -> Case:
    """A case from a scenario YAML text, or from sep 0.1's flat slab keys."""
    import yaml

    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_estimator.design_file import save_design
    from sep_plant.scenario import load_scenario

    sf = root / f'{name}.yaml'
    sf.write_text(yaml_text if yaml_text is not None else
                  yaml.safe_dump({k: (list(v) if isinstance(v, tuple) else v) for k, v in flat_keys.items()}))
    s = load_scenario(sf)
    design = run_design(s.plant, s.problem, DesignSettings(**(settings or {})), show_progress=False,
                        log=lambda m: None)
    df = save_design(root / f'{name}_design.npz', design)
    return Case(s, sf, design, df)


# Fixtures imported into several test modules are instantiated once per module: the cases
# are cached here so that each design is computed once per session.
_CASES: dict[str, Case] = {}


def _cached_case(tmp_path_factory, name: str, **kw) -> Case:
    if name not in _CASES:
        _CASES[name] = make_case(tmp_path_factory.mktemp(f'{name}_case'), name, **kw)
    return _CASES[name]


@pytest.fixture(scope='session')
def small_case(tmp_path_factory) -> Case:
    """n_x = 20, N = 40 scenario (its design takes ~0.2 s)."""
    return _cached_case(tmp_path_factory, 'small', **SMALL)


@pytest.fixture(scope='session')
def reference_case(tmp_path_factory) -> Case:
    """The shipped reference scenario and its design (~8 s)."""
    return _cached_case(tmp_path_factory, 'reference')


@pytest.fixture
def launcher(colcon_install, tmp_path):
    """Starts installed executables; every process is stopped (SIGINT, then SIGKILL of its
    process group) at teardown, and their output is printed (pytest shows it on failure)."""
    lau = Launcher(colcon_install, tmp_path)
    yield lau
    lau.close()
    print(lau.dump())


@pytest.fixture
def probe():
    probes = []

    def make(namespace='sep', name='probe'):
        p = Probe(namespace, name)
        probes.append(p)
        return p
    yield make
    for p in probes:
        p.close()
