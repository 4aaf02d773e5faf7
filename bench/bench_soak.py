"""Soak of one long-running graph (issue 30): plant + lqg + recorder playing episode after episode
in one process each, with faults injected at random steps of random episodes.

Lockstep (default, ``--episodes 1000``): the plant (``episodes`` = E, episode i = Monte Carlo run
i of ``--seed``) talks to the controller through a fault-injecting relay (a node in this process:
plant -> raw_measurements -> relay -> measurements -> controller -> raw_command -> relay -> command
-> plant). Faults, each at a random step 1..N-2 of a random episode (the seeded plan is printed):

* relay: measurements or commands dropped, duplicated, delayed (0.3 s), corrupted (a NaN, or one
  value short);
* lqg_kill: the lqg SIGKILLed and restarted (plant + lqg phase, the first 80 % of the episodes);
* estimator_kill: the estimator SIGKILLed and restarted (plant + estimator + lqr phase, the rest);
* recorder_restart: the recorder stopped (SIGINT) and a new one started on a new bag;
* a design swap every 100 episodes (``next_design_file`` alternating two designs of the scenario;
  the first swap tries a design of another plant first, which must be refused).

Reports: episodes completed / cut off (timeout) per plant status; hangs (no progress for
``--hang-s`` seconds: a step waiting past its timeout without the documented exit); the
fault-free episodes against the offline Monte Carlo of the same seed and runs, each with the
design the controller logged for it (in band identical, inputs to 1e-9); what each fault kind
cost (episodes cut off, equal offline, cost change, wall time); RSS and open fds of every node
at every 50th episode (growth from episode 100 to the end); every bag readable
(`sep_control.bags.episodes.read_episodes`) and every measurement the relay forwarded while a
recorder was recording (from its ready file to its stop) in its bag, the stopped ones' tails too.

Real time (``--real-time-factor 10 --episodes 200``): plant + lqg + recorder, no relay and no
faults; deadline misses counted per episode with the measurement->command latency and the load
average (the cause: commands later than the period).

    PYTHONPATH=sep_plant:sep_estimator:sep_control OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \\
        nice -n 5 .venv/bin/python bench/bench_soak.py --episodes 1000 --out out/soak
"""
from __future__ import annotations

import argparse
import json
import os
import queue
import random
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SMALL = dict(n_x=20, n_steps=40, k_band=24, lqr_k_switch=20)
RELAY_KINDS = ('drop', 'duplicate', 'delay', 'nan', 'wrong_length')
DELAY_S = 0.3
COMMAND_TIMEOUT_S = 3.0
ESTIMATE_TIMEOUT_S = 2.0
MODULES = {'plant': 'sep_plant.ros.plant_node', 'lqg': 'sep_control.ros.lqg_node',
           'estimator': 'sep_estimator.ros.estimator_node', 'lqr': 'sep_control.ros.lqr_node',
           'recorder': 'sep_control.ros.record_node'}


# ------------------------------------------------------------------------------ set-up
def make_designs(out: Path) -> dict[str, Path]:
    """The scenario (n_x 20, N 40) and its designs: 'a', 'b' (other ERA sizes: another ROM and
    gains) and 'bad' (n_x 30: another plant, a swap that must be refused)."""
    import yaml

    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_estimator.design_file import save_design
    from sep_plant.scenario import load_scenario

    files = {}
    for name, keys, settings in (('a', SMALL, {}), ('b', SMALL, {'p': 10, 'q': 10}),
                                 ('bad', {**SMALL, 'n_x': 30}, {})):
        sf = out / f'scenario_{name}.yaml'
        sf.write_text(yaml.safe_dump(keys))
        s = load_scenario(sf)
        d = run_design(s.plant, s.problem, DesignSettings(**settings), show_progress=False, log=lambda m: None)
        files[name] = save_design(out / f'design_{name}.npz', d)
    files['scenario'] = out / 'scenario_a.yaml'
    return files


def node_env() -> dict:
    env = dict(os.environ)
    src = os.pathsep.join(str(ROOT / p) for p in ('sep_plant', 'sep_estimator', 'sep_control'))
    env['PYTHONPATH'] = src + (os.pathsep + env['PYTHONPATH'] if env.get('PYTHONPATH') else '')
    return env


@dataclass
class Fault:
    episode: int
    step: int
    kind: str
    topic: str | None = None      # relay faults: 'measurements' or 'command'
    done: bool = False


def plan_faults(rng: random.Random, episodes: int, n_steps: int, three_from: int, rate: float) -> dict[int, Fault]:
    """Faults at random steps 1..N-2 of a `rate` share of the episodes (never episode 0 nor the
    episodes around the phase switch); process faults a few times each."""
    eps = [e for e in range(1, episodes) if abs(e - three_from) > 3]
    chosen = sorted(rng.sample(eps, int(rate * episodes)))
    kinds = [(k, t) for k in RELAY_KINDS for t in ('measurements', 'command')]
    plan = {e: Fault(e, rng.randint(1, n_steps - 2), *rng.choice(kinds)) for e in chosen}
    procs = [('lqg_kill', [e for e in chosen if e < three_from - 3]),
             ('estimator_kill', [e for e in chosen if e > three_from + 3]),
             ('recorder_restart', chosen)]
    for kind, pool in procs:
        for e in rng.sample(pool, min(3, len(pool))):
            plan[e] = Fault(e, rng.randint(1, n_steps - 2), kind)
    return plan


# ------------------------------------------------------------------------------ processes
class Procs:
    """The node processes (one per role; restarted ones get a new log), each in its own group."""

    def __init__(self, out: Path):
        self.out, self.env = out, node_env()
        self.p: dict[str, subprocess.Popen] = {}
        self.starts: dict[str, int] = {}
        self.history: list[dict] = []           # (role, pid, start, end, rc)

    def start(self, role: str, *args: str, params: dict | None = None, remap: dict | None = None) -> None:
        n = self.starts[role] = self.starts.get(role, 0) + 1
        argv = [sys.executable, '-m', MODULES[role], *args, '--ros-args']
        for k, v in (params or {}).items():
            argv += ['-p', f'{k}:={str(v).lower() if isinstance(v, bool) else v}']
        for k, v in (remap or {}).items():
            argv += ['-r', f'{k}:={v}']
        log = open(self.out / f'{role}{n}.log', 'wb')
        self.p[role] = subprocess.Popen(argv, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, start_new_session=True)
        self.history.append({'role': role, 'pid': self.p[role].pid, 'start': time.time(), 'n': n})

    def send(self, role: str, sig: int) -> None:
        p = self.p.get(role)
        if p is not None and p.poll() is None:
            os.killpg(p.pid, sig)

    def stop(self, role: str, sig: int = signal.SIGINT, grace: float = 10.0) -> int | None:
        p = self.p.pop(role, None)
        if p is None:
            return None
        if p.poll() is None:
            os.killpg(p.pid, sig)
            try:
                p.wait(grace)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)
        self._ended(p)
        return p.returncode

    def _ended(self, p) -> None:
        for h in self.history:
            if h['pid'] == p.pid and 'end' not in h:
                h['end'], h['rc'] = time.time(), p.returncode

    def alive(self, role: str) -> bool:
        p = self.p.get(role)
        return p is not None and p.poll() is None

    def usage(self) -> dict[str, dict]:
        """RSS [kB] and open fds of every live node process."""
        out = {}
        for role, p in self.p.items():
            try:
                rss = next(int(line.split()[1]) for line in open(f'/proc/{p.pid}/status') if line.startswith('VmRSS'))
                out[role] = {'pid': p.pid, 'rss_kb': rss, 'fds': len(os.listdir(f'/proc/{p.pid}/fd'))}
            except (OSError, StopIteration):
                pass
        return out

    def stop_all(self) -> None:
        for role in list(self.p):
            self.stop(role, grace=5.0)


# ------------------------------------------------------------------------------ relay
class Relay:
    """The fault-injecting relay (an rclpy node of this process, spun by a thread): forwards
    raw_measurements -> measurements and raw_command -> command, applying the plan's relay
    faults; tells the orchestrator about episode announcements and process faults (`events`)."""

    def __init__(self, plan: dict[int, Fault], relay: bool):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from std_msgs.msg import String

        from sep_plant.ros import contract as c

        self.c, self.plan, self.events = c, plan, queue.Queue()
        self.node = node = rclpy.create_node('soak_relay', namespace='sep')
        self.episode, self.dt_ns = -1, None
        self.forwarded: list[tuple[int, int, float]] = []    # (episode, step, time) of forwarded measurements
        self.t_progress = time.monotonic()
        node.create_subscription(String, c.SCENARIO, self._on_scenario, c.SCENARIO_QOS)
        if relay:
            self.pub_y = node.create_publisher(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS, c.LOOP_QOS)
            self.pub_u = node.create_publisher(c.TOPIC_TYPES[c.COMMAND], c.COMMAND, c.LOOP_QOS)
            node.create_subscription(c.TOPIC_TYPES[c.MEASUREMENTS], 'raw_measurements', self._on_y, c.LOOP_QOS)
            self.sub_u = node.create_subscription(c.TOPIC_TYPES[c.COMMAND], 'raw_command', self._on_u, c.LOOP_QOS)
        else:       # real time: only watch the loop
            node.create_subscription(c.TOPIC_TYPES[c.MEASUREMENTS], c.MEASUREMENTS, self._on_watch, c.LOOP_QOS)
        self.clients: dict[str, object] = {}
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(node)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self.stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def _on_scenario(self, msg) -> None:
        from sep_plant.scenario import scenario_message_parts

        _, info, _, ep = scenario_message_parts(msg.data)
        self.dt_ns = self.c.dt_ns(info.dt)
        if ep is not None and ep['index'] != self.episode:
            self.episode = ep['index']
            self.t_progress = time.monotonic()
            self.events.put(('episode', ep['index'], time.time()))

    def _step(self, msg) -> int:
        return self.c.time_ns(msg.header.stamp) // self.dt_ns if self.dt_ns else -1

    def _fault(self, k: int, topic: str) -> Fault | None:
        f = self.plan.get(self.episode)
        if f is None or f.done or f.step != k:
            return None
        if f.topic is None:                  # a process fault: at measurement k
            if topic == 'measurements':
                f.done = True
                self.events.put(('fault', f, time.time()))
            return None
        if f.topic != topic:
            return None
        f.done = True
        return f

    def _on_watch(self, msg) -> None:
        self.t_progress = time.monotonic()

    def _on_y(self, msg) -> None:
        k = self._step(msg)
        self.t_progress = time.monotonic()
        f = self._fault(k, 'measurements')
        if self._forward(msg, 'position', self.pub_y, f):
            self.forwarded.append((self.episode, k, time.time()))

    def _on_u(self, msg) -> None:
        self._forward(msg, 'effort', self.pub_u, self._fault(self._step(msg), 'command'))

    @staticmethod
    def _forward(msg, key: str, pub, f: Fault | None) -> bool:
        """Publish `msg` with the fault `f` applied; whether it went out at once."""
        kind = f.kind if f is not None else None
        if kind == 'drop':
            return False
        if kind == 'delay':
            threading.Timer(DELAY_S, pub.publish, [msg]).start()
            return False
        if kind == 'nan':
            setattr(msg, key, [float('nan'), *list(getattr(msg, key))[1:]])
        elif kind == 'wrong_length':
            setattr(msg, key, list(getattr(msg, key))[:-1])
        pub.publish(msg)
        if kind == 'duplicate':
            pub.publish(msg)
        return True

    def set_param(self, node: str, value: str, timeout: float = 5.0) -> tuple[bool, str]:
        """Set next_design_file on `node` (tries twice: a first response can be lost to discovery)."""
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
        from rcl_interfaces.srv import SetParameters

        cli = self.clients.get(node) or self.node.create_client(SetParameters, f'{node}/set_parameters')
        self.clients[node] = cli
        req = SetParameters.Request(parameters=[Parameter(name='next_design_file', value=ParameterValue(
            type=ParameterType.PARAMETER_STRING, string_value=value))])
        for _ in range(2):
            if not cli.wait_for_service(timeout_sec=timeout):
                continue
            fut = cli.call_async(req)
            t_end = time.monotonic() + timeout
            while not fut.done() and time.monotonic() < t_end:
                time.sleep(0.005)
            if fut.done():
                r = fut.result().results[0]
                return r.successful, r.reason
        return False, 'no answer'

    def counts(self) -> tuple[int, int]:
        """(subscribers of measurements, publishers of raw_command)."""
        return (self.node.count_subscribers(f'/sep/{self.c.MEASUREMENTS}'),
                self.node.count_publishers('/sep/raw_command'))

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.node.destroy_node()


# ------------------------------------------------------------------------------ the soak
@dataclass
class Soak:
    """The running soak: processes, relay, what happened."""

    args: argparse.Namespace
    out: Path
    files: dict[str, Path]
    procs: Procs
    relay: Relay
    plan: dict[int, Fault]
    three_from: int
    design: str = 'a'
    mode: str = 'lqg'
    bags: list[dict] = field(default_factory=list)
    swaps: list[dict] = field(default_factory=list)
    usage: dict[int, dict] = field(default_factory=dict)
    faults_done: list[dict] = field(default_factory=list)
    hangs: list[dict] = field(default_factory=list)
    load: dict[int, float] = field(default_factory=dict)     # 1-minute load average at each episode's start

    # ------------------------------------------------------------ nodes
    def ctl_params(self, role: str) -> dict:
        p = {'design_file': self.files[self.design], 'wait_for_scenario_s': 120.0,
             'episode_log_file': self.out / 'controllers.jsonl',
             'summary_file': self.out / f'{role}{self.procs.starts.get(role, 0) + 1}.json'}
        if role == 'lqr':
            p['estimate_timeout_s'] = ESTIMATE_TIMEOUT_S
        return p

    def start_controllers(self) -> None:
        remap = {'command': 'raw_command'} if self.args.real_time_factor is None else None
        if self.mode == 'lqg':
            self.procs.start('lqg', params=self.ctl_params('lqg'), remap=remap)
        else:
            self.procs.start('estimator', params=self.ctl_params('estimator'))
            self.procs.start('lqr', params=self.ctl_params('lqr'), remap=remap)

    def start_recorder(self) -> None:
        n = len(self.bags)
        bag, ready = self.out / f'bag{n}', self.out / f'ready{n}'
        self.procs.start('recorder', '--out', str(bag), '--ready-file', str(ready), '--no-stop-at-end',
                         '--topics', 'scenario', 'measurements', 'command', 'applied_input',
                         '--ready-topics', *(('measurements', 'command') if self.relay_on else ('command',)))
        self.bags.append({'bag': str(bag), 'ready_file': str(ready), 't_start': time.time()})

    @property
    def relay_on(self) -> bool:
        return self.args.real_time_factor is None

    def wait_ready(self, timeout: float = 120.0) -> None:
        """The recorder's ready file, and the controller subscribed (before the plant starts)."""
        t_end = time.monotonic() + timeout
        rec = self.bags[-1]
        while not Path(rec['ready_file']).exists():
            if time.monotonic() > t_end:
                raise RuntimeError('the recorder did not get ready')
            time.sleep(0.05)
        rec['t_ready'] = Path(rec['ready_file']).stat().st_mtime

    def start_plant(self) -> None:
        a = self.args
        params = {'scenario_file': self.files['scenario'], 'seed': a.seed, 'run': 0, 'episodes': a.episodes,
                  'episode_log_file': self.out / 'plant_episodes.jsonl', 'summary_file': self.out / 'plant.json',
                  'trajectory_file': self.out / 'traj' / 'traj.npz', 'start_timeout_s': 120.0,
                  'wait_for_subscribers': 1 if self.relay_on else 2}
        if a.real_time_factor is None:
            params.update(mode='lockstep', command_timeout_s=COMMAND_TIMEOUT_S)
        else:
            params.update(mode='realtime', real_time_factor=a.real_time_factor)
        self.procs.start('plant', params=params,
                         remap={'measurements': 'raw_measurements'} if self.relay_on else None)

    # ------------------------------------------------------------ events
    def on_episode(self, e: int, t: float) -> None:
        self.load[e] = os.getloadavg()[0]
        if e % 50 == 0 or e == self.args.episodes - 1:
            self.usage[e] = self.procs.usage()
        if e == self.three_from and self.relay_on:
            self.switch_to_three_nodes()
        every = self.args.swap_every
        if e % every == every // 2 and self.relay_on:
            self.swap(e)

    def switch_to_three_nodes(self) -> None:
        self.procs.stop('lqg')
        self.mode = 'estimator+lqr'
        self.start_controllers()

    def swap(self, e: int) -> None:
        """next_design_file on the nodes that own a design: the other design (first: a refused one)."""
        nodes = ['/sep/estimator'] + (['/sep/lqr'] if self.mode != 'lqg' else [])
        if not self.swaps:
            ok, why = self.relay.set_param('/sep/estimator', str(self.files['bad']))
            self.swaps.append({'episode': e, 'design': 'bad', 'accepted': ok, 'reason': why})
        new = 'b' if self.design == 'a' else 'a'
        results = [self.relay.set_param(n, str(self.files[new])) for n in nodes]
        ok = all(r[0] for r in results)
        self.swaps.append({'episode': e, 'design': new, 'accepted': ok, 'reason': '; '.join(r[1] for r in results)})
        if ok:
            self.design = new        # a restarted controller starts with it

    def on_fault(self, f: Fault, t: float) -> None:
        rec = {'episode': f.episode, 'step': f.step, 'kind': f.kind, 't': t}
        if f.kind == 'lqg_kill' and self.mode == 'lqg':
            self.procs.stop('lqg', signal.SIGKILL)
            self.procs.start('lqg', params=self.ctl_params('lqg'), remap={'command': 'raw_command'})
        elif f.kind == 'estimator_kill' and self.mode != 'lqg':
            self.procs.stop('estimator', signal.SIGKILL)
            self.procs.start('estimator', params=self.ctl_params('estimator'))
        elif f.kind == 'recorder_restart':
            self.bags[-1]['t_stop'] = time.time()
            self.bags[-1]['rc'] = self.procs.stop('recorder')
            self.start_recorder()
        else:
            rec['skipped'] = f'not in mode {self.mode}'
        self.faults_done.append(rec)

    def run(self) -> float:
        """Spin until the plant exits (or a hang); the seconds it took."""
        t0 = time.monotonic()
        while self.procs.alive('plant'):
            try:
                ev = self.relay.events.get(timeout=0.05)
            except queue.Empty:
                ev = None
            if ev is not None:
                (self.on_episode if ev[0] == 'episode' else self.on_fault)(ev[1], ev[2])
            idle = time.monotonic() - self.relay.t_progress
            if idle > self.args.hang_s:
                self.hang(idle)
                break
        return time.monotonic() - t0

    def hang(self, idle: float) -> None:
        """No progress for hang_s: stacks of every node into its log, recorded, the soak ends."""
        for role in list(self.procs.p):
            self.procs.send(role, signal.SIGUSR1)
        self.hangs.append({'episode': self.relay.episode, 'idle_s': idle, 'alive': list(self.procs.p)})
        time.sleep(1.0)


# ------------------------------------------------------------------------------ analysis
def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def design_of_episodes(out: Path, files: dict[str, Path]) -> dict[int, str]:
    """Episode -> design name ('a'/'b'), from the controllers' records; 'mixed' when the nodes of
    an episode ran different designs (three-node mode)."""
    names = {str(p): n for n, p in files.items()}
    by_ep: dict[int, set] = {}
    for r in read_jsonl(out / 'controllers.jsonl'):
        if r.get('episode') is not None and r['last_step'] >= 0:
            by_ep.setdefault(r['episode'], set()).add(names.get(r['design_file'], '?'))
    return {e: (s.pop() if len(s) == 1 else 'mixed') for e, s in by_ep.items()}


def compare_offline(out: Path, files: dict[str, Path], seed: int, eps: list[int], designs: dict[int, str]) -> dict:
    """Fault-free completed episodes against the offline Monte Carlo of their runs with their design:
    {episode: (in band equal, max |U - U_offline|, J, J_offline)}."""
    from sep_control.evaluation.metrics import in_band
    from sep_control.evaluation.montecarlo import simulate
    from sep_estimator.design_file import load_design
    from sep_plant.scenario import load_scenario

    plant = load_scenario(files['scenario']).plant
    res = {}
    for name in ('a', 'b'):
        mine = [e for e in eps if designs.get(e) == name]
        if not mine:
            continue
        d = load_design(files[name])
        ref = simulate(plant, d, 'rom_lqg', seed, mine)
        for i, e in enumerate(mine):
            tr = np.load(out / 'traj' / f'traj.e{e}.npz')
            band = bool(in_band(tr['F'], d.objective)) == bool(in_band(ref.F[i], d.objective))
            res[e] = (band, float(np.max(np.abs(tr['U'] - ref.U[i]))),
                      float(d.objective.cost(tr['F'], tr['U'])), float(d.objective.cost(ref.F[i], ref.U[i])))
    return res


def check_bags(soak: Soak) -> list[dict]:
    """Each bag readable, with every measurement the relay forwarded while it recorded (from its
    ready file + 0.5 s to its stop - 0.05 s) in it."""
    from sep_control.bags.episodes import read_episodes
    from sep_control.bags.storage import read_raw
    from sep_plant import topics as T

    out = []
    fwd = np.array(soak.relay.forwarded or [(0, 0, 0.0)], dtype=float)
    for b in soak.bags:
        row = {'bag': Path(b['bag']).name}
        t0 = time.perf_counter()
        ready = Path(b['ready_file'])
        lo = (ready.stat().st_mtime if ready.exists() else float('inf')) + 0.5
        hi = b.get('t_stop', float('inf')) - 0.05
        want = {(int(x[0]), int(x[1])) for x in fwd if lo <= x[2] <= hi}
        try:
            raw = read_raw(b['bag'])
            eps = read_episodes(b['bag'], allow_truncated=False) if len(raw) else []
        except Exception as exc:  # noqa: BLE001 - reported
            row.update(readable=False, error=f'{type(exc).__name__}: {exc}')
            out.append(row)
            continue
        have = set()
        for e in eps:
            stamps = e.episode.times[T.MEASUREMENTS].stamp_ns if T.MEASUREMENTS in e.episode.times else []
            have |= {(e.index, int(round(s / (e.episode.dt * 1e9)))) for s in stamps}
        ready = Path(b['ready_file'])
        missing = sorted(want - have)
        row.update(readable=raw.complete, messages=len(raw), read_s=time.perf_counter() - t0, episodes=len(eps),
                   stopped_by_fault='t_stop' in b,
                   forwarded_while_recording=len(want), missing=len(missing), missing_first=missing[:5])
        out.append(row)
    return out


def fault_costs(plant_eps: dict[int, dict], soak_plan: dict[int, Fault]) -> dict:
    """Per fault kind: episodes, cut off, mean wall time of the episode."""
    out: dict[str, dict] = {}
    for e, f in soak_plan.items():
        key = f'{f.kind}:{f.topic}' if f.topic else f.kind
        rec = plant_eps.get(e)
        row = out.setdefault(key, {'episodes': 0, 'cut_off': 0, 'wall_s': []})
        row['episodes'] += 1
        if rec is None:
            continue
        row['cut_off'] += rec['status'] != 'completed'
        row['wall_s'].append(rec['t_end'] - rec['t_start'])
    for row in out.values():
        row['wall_s_mean'] = float(np.mean(row.pop('wall_s'))) if row.get('wall_s') else None
    return out


def summarize(soak: Soak, wall_s: float) -> dict:
    out, files, a = soak.out, soak.files, soak.args
    plant_eps = {r['episode']: r for r in read_jsonl(out / 'plant_episodes.jsonl')}
    by_status: dict[str, int] = {}
    for r in plant_eps.values():
        by_status[r['status']] = by_status.get(r['status'], 0) + 1
    walls = [r['t_end'] - r['t_start'] for r in plant_eps.values()]
    rep = {'episodes_asked': a.episodes, 'episodes_played': len(plant_eps), 'by_status': by_status,
           'episode_wall_s_max': max(walls, default=None),
           'wall_s': wall_s, 'hangs': soak.hangs,
           'plant_rc': next(h.get('rc') for h in soak.procs.history if h['role'] == 'plant'),
           'swaps': soak.swaps, 'faults_injected': len(soak.faults_done) + sum(
               1 for f in soak.plan.values() if f.topic and f.done),
           'usage': soak.usage, 'processes': soak.procs.history}
    if a.real_time_factor is not None:
        rep['realtime'] = realtime_report(plant_eps, soak.load)
        return rep
    designs = design_of_episodes(out, files)
    free = [e for e, r in plant_eps.items() if e not in soak.plan]
    done = [e for e in free if plant_eps[e]['status'] == 'completed' and designs.get(e) in ('a', 'b')]
    cmp = compare_offline(out, files, a.seed, done, designs)
    equal = [e for e, (band, du, _, _) in cmp.items() if band and du <= 1e-9]
    rep['fault_free'] = {'episodes': len(free), 'completed': len(done), 'equal_offline': len(equal),
                         'not_completed': {e: cause_of(e, plant_eps[e], soak, designs)
                                           for e in sorted(set(free) - set(done))},
                         'not_equal': sorted((e, cmp[e][1]) for e in set(cmp) - set(equal))[:20],
                         'mixed_designs': sorted(e for e in free if designs.get(e) == 'mixed')}
    rep['fault_costs'] = fault_costs(plant_eps, soak.plan)
    rep['fault_cost_J'] = fault_j(soak.plan, out, files, a.seed, designs, plant_eps)
    rep['bags'] = check_bags(soak)
    return rep


def cause_of(e: int, rec: dict, soak: Soak, designs: dict[int, str]) -> str:
    """Why a fault-free episode was not completed: no controller took a step of it, or a controller
    process had started shortly before it ended (its first command sent before its writer matched
    the relay's reader: lost to discovery), or unexplained; with the last event before it."""
    events = [(f.episode, f"{f.kind}{':' + f.topic if f.topic else ''}") for f in soak.plan.values() if f.episode < e]
    if soak.three_from <= e:
        events.append((soak.three_from, 'switch to estimator + lqr'))
    last = max(events) if events else None
    after = f' (after {last[1]} in episode {last[0]})' if last else ''
    if e not in designs:
        return 'no controller took a step' + after
    started = [h for h in soak.procs.history if h['role'] in ('lqg', 'estimator', 'lqr')
               and 0 <= rec['t_end'] - h['start'] <= 10.0]
    if started:
        h = max(started, key=lambda h: h['start'])
        return (f"{h['role']} process started {rec['t_start'] - h['start']:.1f} s before the episode: a command "
                f"sent before its writer matched" + after)
    return 'unexplained' + after


def fault_j(plan, out, files, seed, designs, plant_eps) -> dict:
    """Per relay fault kind of completed episodes: mean relative cost change J/J_offline - 1 and
    how many equal the offline run (U to 1e-9)."""
    eps = [e for e in plan if plant_eps.get(e, {}).get('status') == 'completed' and designs.get(e) in ('a', 'b')]
    cmp = compare_offline(out, files, seed, eps, designs)
    res: dict[str, dict] = {}
    for e, (band, du, J, J0) in cmp.items():
        f = plan[e]
        row = res.setdefault(f'{f.kind}:{f.topic}' if f.topic else f.kind, {'completed': 0, 'equal': 0, 'dJ': []})
        row['completed'] += 1
        row['equal'] += bool(band and du <= 1e-9)
        row['dJ'].append(J / J0 - 1.0)
    for row in res.values():
        dj = row.pop('dJ')
        row['dJ_rel_mean'], row['dJ_rel_max'] = float(np.mean(dj)), float(np.max(dj))
    return res


def realtime_report(plant_eps: dict[int, dict], load: dict[int, float]) -> dict:
    """Deadline misses, and what tells their cause: the measurement->command latency (p99) and the
    machine's load average in the episodes with misses and in those without."""
    eps = sorted(plant_eps)
    misses = np.array([plant_eps[e]['deadline_misses'] for e in eps])
    p99 = np.array([plant_eps[e]['latency_p99_s'] or np.nan for e in eps])
    la = np.array([load.get(e, np.nan) for e in eps])
    hit = misses > 0

    def med(a, m):
        return float(np.nanmedian(a[m])) if m.any() else None
    return {'deadline_misses': int(misses.sum()), 'episodes_with_misses': int(hit.sum()),
            'latency_p99_s_median': {'with_misses': med(p99, hit), 'without': med(p99, ~hit)},
            'loadavg_median': {'with_misses': med(la, hit), 'without': med(la, ~hit)},
            'cpus': os.cpu_count()}


def growth(usage: dict[int, dict]) -> dict:
    """RSS and fds of every node process (role, pid) from its first sample at episode >= 100 to its
    last (samples at every 50th episode and the last): the processes that lived through the soak
    and the restarted ones alike."""
    out = {}
    for e in sorted(int(k) for k in usage):
        for role, u in usage[e if e in usage else str(e)].items():
            if e >= 100:
                out.setdefault(f"{role}[{u['pid']}]", []).append((e, u['rss_kb'], u['fds']))
    return {key: {'episodes': (s[0][0], s[-1][0]), 'rss_kb': (s[0][1], s[-1][1]),
                  'rss_growth_pct': 100.0 * (s[-1][1] / s[0][1] - 1), 'fds': (s[0][2], s[-1][2])}
            for key, s in out.items() if len(s) >= 2}


# ------------------------------------------------------------------------------ main
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--episodes', type=int, default=1000)
    p.add_argument('--seed', type=int, default=11)
    p.add_argument('--fault-seed', type=int, default=5)
    p.add_argument('--fault-rate', type=float, default=0.08, help='share of episodes with a fault (lockstep)')
    p.add_argument('--real-time-factor', type=float, default=None,
                   help='real-time soak at this factor (no relay, no faults)')
    p.add_argument('--swap-every', type=int, default=100, help='a design swap every this many episodes')
    p.add_argument('--hang-s', type=float, default=30.0, help='no progress this long is a hang')
    p.add_argument('--out', type=Path, default=ROOT / 'out' / time.strftime('soak-%Y%m%d-%H%M%S'),
                   help='a new folder for the logs, bags and report.json (default out/soak-<time>)')
    return p.parse_args(argv)


def setup(a: argparse.Namespace) -> Soak:
    import rclpy

    a.out.mkdir(parents=True, exist_ok=False)
    (a.out / 'traj').mkdir()
    files = make_designs(a.out)
    three_from = int(0.8 * a.episodes)
    plan = {} if a.real_time_factor is not None else plan_faults(
        random.Random(a.fault_seed), a.episodes, SMALL['n_steps'], three_from, a.fault_rate)
    (a.out / 'plan.json').write_text(json.dumps({e: vars(f) for e, f in sorted(plan.items())}, indent=1))
    rclpy.init()
    soak = Soak(a, a.out, files, Procs(a.out), Relay(plan, a.real_time_factor is None), plan, three_from)
    soak.start_recorder()
    soak.start_controllers()
    soak.wait_ready()
    t_end = time.monotonic() + 120
    while soak.relay_on and soak.relay.counts() < (2, 1):      # lqg + recorder on measurements
        assert time.monotonic() < t_end, 'the controller did not come up'
        time.sleep(0.1)
    soak.start_plant()
    return soak


def main(argv=None) -> int:
    a = parse_args(argv)
    os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(150, 230)))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    soak = setup(a)
    try:
        wall = soak.run()
        soak.procs.stop('plant', grace=30.0)
        time.sleep(2.0)           # the controllers and the recorder end after the last episode
    finally:
        soak.procs.stop_all()
    rep = summarize(soak, wall)
    rep['growth'] = growth(soak.usage)
    (a.out / 'report.json').write_text(json.dumps(rep, indent=1, default=str))
    print_report(rep)
    soak.relay.close()
    return 0


def print_report(rep: dict) -> None:
    print(f"episodes played {rep['episodes_played']}/{rep['episodes_asked']} in {rep['wall_s']:.0f} s: "
          f"{rep['by_status']}; hangs {len(rep['hangs'])}; plant exit code {rep['plant_rc']}; longest episode "
          f"{rep['episode_wall_s_max']:.2f} s")
    if 'realtime' in rep:
        print('real time:', json.dumps(rep['realtime']))
    else:
        print('fault-free:', json.dumps(rep['fault_free']))
        print('faults injected:', rep['faults_injected'])
        for k, v in sorted(rep['fault_costs'].items()):
            print(f'  {k:28s} {json.dumps(v)}  J: {json.dumps(rep["fault_cost_J"].get(k))}')
        print('swaps:', json.dumps([{k: s[k] for k in ('episode', 'design', 'accepted')} for s in rep['swaps']]))
        for b in rep['bags']:
            print('bag:', json.dumps(b))
    for role, g in sorted(rep['growth'].items()):
        print(f'  {role:10s} {json.dumps(g)}')


if __name__ == '__main__':
    sys.exit(main())
