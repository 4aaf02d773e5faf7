"""Latency and compute benchmark of the online loop (issue 3 acceptance).

Measured in one run, on this machine:

1. bare rclpy ping-pong between two processes: JointState with 5 named float64 values out
   (the size of measurements), JointState with 5 named values back (command),
   same QoS (reliable, keep-last 10), a SingleThreadedExecutor spin_once loop on the pinging
   side exactly like the plant's;
2. the measurement-to-command round trip through plant <-> lqg (two processes, lockstep, the
   reference design), as measured by the plant (publish of y_k -> command k received), and
   the same in real time at real_time_factor 10;
3. per-step compute of estimator + LQR (the pure calls: KF update, LQR law, KF predict; and
   the node's per-step work with field reconstruction and message building), with BLAS
   limited to 1 thread (what the nodes do) and with the default thread pools.

Prints a table with ratios; ``--json PATH`` writes the numbers.  Targets: round trip within
1.5x of the bare ping-pong, compute under 50 us per step.

    PYTHONPATH=sep_plant:sep_estimator:sep_control python bench/bench_latency.py
"""
from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def _env() -> dict:
    env = dict(os.environ)
    src = os.pathsep.join(str(ROOT / p) for p in ('sep_plant', 'sep_estimator', 'sep_control'))
    env['PYTHONPATH'] = src + (os.pathsep + env['PYTHONPATH'] if env.get('PYTHONPATH') else '')
    env.setdefault('ROS_DOMAIN_ID', str(random.randint(102, 200)))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    return env


def pct(a) -> dict:
    a = np.asarray(a, dtype=float)
    if a.size == 0:
        return {'p50': None, 'p99': None, 'mean': None, 'n': 0}
    return {'p50': float(np.percentile(a, 50)), 'p99': float(np.percentile(a, 99)),
            'mean': float(a.mean()), 'n': int(a.size)}


# ------------------------------------------------------------------------- ping-pong
def pong_main(executor: str) -> int:
    import rclpy
    from rclpy.node import Node

    from sep_plant.ros import contract as c
    from sep_plant.ros.base import make_executor

    rclpy.init()
    node = Node('pong')
    names = [f'input_{j}' for j in range(5)]
    pub = node.create_publisher(c.TOPIC_TYPES[c.COMMAND], 'bench_pong', c.LOOP_QOS)

    def on_ping(msg):
        out = c.TOPIC_TYPES[c.COMMAND]()
        out.header = msg.header
        out.name = names
        out.effort = np.asarray(msg.position) * 0.5
        pub.publish(out)

    node.create_subscription(c.TOPIC_TYPES[c.MEASUREMENTS], 'bench_ping', on_ping, c.LOOP_QOS)
    ex = make_executor(executor)
    ex.add_node(node)
    try:
        while rclpy.ok():
            ex.spin_once(timeout_sec=0.5)
    except (KeyboardInterrupt, Exception):  # noqa: BLE001 - killed by the parent
        pass
    return 0


def ping_pong(n: int, env: dict, executor: str, period: float = 0.0) -> dict:
    """Round trips back to back (period 0, like lockstep) or one every `period` seconds."""
    import rclpy
    from rclpy.node import Node

    from sep_plant.ros import contract as c
    from sep_plant.ros.base import make_executor

    pong = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), '--pong', executor],
                            env=env, start_new_session=True)
    try:
        rclpy.init()
        node = Node('ping')
        ex = make_executor(executor)
        ex.add_node(node)
        got = {}
        pub = node.create_publisher(c.TOPIC_TYPES[c.MEASUREMENTS], 'bench_ping', c.LOOP_QOS)
        node.create_subscription(c.TOPIC_TYPES[c.COMMAND], 'bench_pong',
                                 lambda m: got.__setitem__(c.step_of_stamp(m.header.stamp, 0.25),
                                                           time.perf_counter()), c.LOOP_QOS)
        sensors = [f'sensor_{j}' for j in range(5)]
        t_end = time.perf_counter() + 30
        while pub.get_subscription_count() < 1 and time.perf_counter() < t_end:
            ex.spin_once(timeout_sec=0.05)
        ex.spin_once(timeout_sec=0.5)
        rtt = []
        y = np.linspace(149, 151, 5)
        t_start = time.perf_counter()
        for k in range(n + 50):
            if period:
                while time.perf_counter() < t_start + k * period:
                    ex.spin_once(timeout_sec=max(0.0, t_start + k * period - time.perf_counter()))
            t0 = time.perf_counter()
            pub.publish(c.joint_state(k, 0.25, sensors, position=y))
            while k not in got and time.perf_counter() - t0 < 2.0:
                ex.spin_once(timeout_sec=2.0)
            if k in got and k >= 50:          # 50 warm-up round trips
                rtt.append(got[k] - t0)
        node.destroy_node()
        rclpy.shutdown()
        return pct(rtt)
    finally:
        pong.kill()
        pong.wait()


# ------------------------------------------------------------------------ plant <-> lqg
def loop_round_trip(design_file: Path, scenario_file: Path | None, env: dict, mode: str,
                    tmp: Path, executor: str) -> dict:
    summary = tmp / f'plant_{mode}_{executor}.json'
    scen = ['-p', f'scenario_file:={scenario_file}'] if scenario_file else []
    lqg = subprocess.Popen([sys.executable, '-m', 'sep_control.ros.lqg_node', '--executor', executor, '--ros-args',
                            '-p', f'design_file:={design_file}'], env=env,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        rc = subprocess.run([sys.executable, '-m', 'sep_plant.ros.plant_node', '--executor', executor,
                             '--summary-json', str(summary),
                             '--ros-args', *scen, '-p', f'mode:={mode}', '-p', 'real_time_factor:=10.0',
                             '-p', 'publish_field:=true'], env=env, capture_output=True, text=True,
                            timeout=300).returncode
        if rc != 0:
            raise RuntimeError(f'plant exited {rc}')
        lqg.wait(timeout=30)
    finally:
        if lqg.poll() is None:
            lqg.kill()
            lqg.wait()
    s = json.loads(summary.read_text())
    return {'p50': s['latency_p50_s'], 'p99': s['latency_p99_s'], 'max': s['latency_max_s'],
            'deadline_misses': s['deadline_misses'], 'n': s['n_steps']}


# ---------------------------------------------------------------------------- compute
def compute_per_step(design, repeats: int = 20) -> dict:
    """Per-step compute of the estimator core + LQR law ('core'), and with the messages the lqg
    builds (command, estimate, field cloud) ('node')."""
    from sep_control.control.controllers import make_controller
    from sep_estimator.estimator_core import EstimatorCore
    from sep_plant.ros import contract as c

    info, nom = design.info, design.nominal
    N = design.n_steps
    law = make_controller('rom_lqg', design.lqg, design.problem, nom.u)
    rng = np.random.default_rng(0)
    y = nom.y + rng.normal(0, 1, (N + 1, info.n_y))
    labels = c.state_labels(design.n_r, design.lqg.n_d)
    names = list(info.input_names)
    cloud = c.CloudBuilder(design.field_xyz, info.field_name)
    core, node = [], []
    for _ in range(repeats):
        for build_messages, out in ((False, core), (True, node)):
            est = EstimatorCore(design.lqg, nom.u, nom.y, nom.field)
            for k in range(N + 1):
                t0 = time.perf_counter()
                a, _ = est.measurement(k, y[k])
                if k < N:
                    u = law.command(k, a)
                    if build_messages:
                        c.joint_state(k, info.dt, names, effort=u)
                if build_messages:
                    c.joint_state(k, info.dt, labels, position=a)
                    f, std = est.field_estimate()
                    cloud.build(k, info.dt, f, std)
                if k < N:
                    est.applied(k, u)
                out.append(time.perf_counter() - t0)
    return {'core': pct(core), 'node': pct(node)}


def compute_mpc(design, plant, runs: int = 10, horizon: int = 20) -> dict:
    """Per-step time of the feedback law alone on closed-loop estimates (plant + KF, one run at a
    time, the online path): the clipped LQR law vs the ROM-MPC law (its steps without an
    active limit and those that solve a QP separately)."""
    from sep_control.control.controllers import MpcOptions, make_controller
    from sep_estimator.estimator_core import EstimatorCore
    from sep_plant.noise import noise_sequences

    info, nom, problem = design.info, design.nominal, design.problem
    N = design.n_steps
    lo, hi = problem.limits(info.n_u)
    lqr = make_controller('rom_lqg', design.lqg, problem, nom.u)
    mpc = make_controller('rom_mpc', design.lqg, problem, nom.u, MpcOptions(horizon=horizon))
    t_lqr, t_free, t_qp = [], [], []
    for run in range(runs):
        w, v = noise_sequences(problem, info, 1, [run])
        est = EstimatorCore(design.lqg, nom.u, nom.y, nom.field)
        mpc.reset()                          # a new episode: no warm start from the last run
        x = plant.initial_state(1)
        for k in range(N):
            a, _ = est.measurement(k, plant.observe(x)[0] + v[0, k])
            t0 = time.perf_counter()
            lqr.command(k, a)
            t_lqr.append(time.perf_counter() - t0)
            qp = mpc.stats.qp + mpc.stats.fallbacks
            t0 = time.perf_counter()
            u = mpc.command(k, a)
            (t_qp if mpc.stats.qp + mpc.stats.fallbacks > qp else t_free).append(time.perf_counter() - t0)
            est.applied(k, u)
            x = plant.step(x, u[None], w[:, k])
    return {'lqr': pct(t_lqr), 'mpc_free': pct(t_free), 'mpc_qp': pct(t_qp), 'mpc_all': pct(t_free + t_qp),
            'qp_share': len(t_qp) / max(1, len(t_free) + len(t_qp)), 'fallbacks': mpc.stats.fallbacks,
            'horizon': mpc.horizon, 'n_r': design.n_r, 'limits': [float(lo.min()), float(hi.max())]}


def compute_threads(design) -> dict:
    from threadpoolctl import threadpool_info, threadpool_limits
    default = compute_per_step(design)
    with threadpool_limits(limits=1):
        one = compute_per_step(design)
    pools = [f"{p['internal_api']}:{p['num_threads']}" for p in threadpool_info()]
    return {'blas_1': one, 'blas_default': default, 'pools': pools}


# ------------------------------------------------------------------------------- main
def fmt(v) -> str:
    return '-' if v is None else (f'{v * 1e3:8.3f} ms' if v >= 1e-3 else f'{v * 1e6:8.1f} us')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument('--design', type=Path, help='design file of the reference scenario (default: design it, ~8 s)')
    ap.add_argument('--scenario', type=Path, help='scenario file of --design (default: reference)')
    ap.add_argument('--pings', type=int, default=500, help='ping-pong round trips')
    ap.add_argument('--no-realtime', action='store_true', help='skip the 6.25 s real-time episode')
    ap.add_argument('--json', type=Path, help='write the results as JSON')
    ap.add_argument('--mpc-limits', type=float, nargs=2, default=[0.0, 0.6], metavar=('U_MIN', 'U_MAX'),
                    help='input limits of the design the MPC compute row uses (designed here, ~8 s)')
    ap.add_argument('--pong', choices=('events', 'single'), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.pong:
        return pong_main(args.pong)
    env = _env()
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')})
    from sep_estimator.design_file import load_design, save_design
    from sep_plant.scenario import load_scenario

    tmp = Path(tempfile.mkdtemp(prefix='sep_bench_latency_'))
    scenario = load_scenario(args.scenario)
    if args.design:
        design_file = args.design
        design = load_design(design_file, expect_scenario=scenario)
    else:
        from sep_control.design.pipeline import run_design
        t0 = time.perf_counter()
        design = run_design(scenario.plant, scenario.problem, show_progress=False, log=lambda m: None)
        design_file = save_design(tmp / 'design.npz', design)
        print(f'design: {time.perf_counter() - t0:.1f} s (n_x={design.info.n_x}, N={design.n_steps}, n_r={design.n_r})')

    print(f'ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]}, {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.2f}')
    res = {}
    period = design.info.dt / 10.0
    for ex in ('events', 'single'):
        res[f'ping_pong_{ex}'] = ping_pong(args.pings, env, ex)
        res[f'loop_lockstep_{ex}'] = loop_round_trip(design_file, args.scenario, env, 'lockstep', tmp, ex)
    if not args.no_realtime:
        res['ping_pong_paced_events'] = ping_pong(min(args.pings, 250), env, 'events', period)
        res['loop_realtime_rtf10_events'] = loop_round_trip(design_file, args.scenario, env, 'realtime',
                                                            tmp, 'events')
    res['ping_pong_events_after'] = ping_pong(args.pings, env, 'events')
    res['compute'] = compute_threads(design)
    from sep_control.design.pipeline import run_design
    lim = scenario.replace(u_min=args.mpc_limits[0], u_max=args.mpc_limits[1])
    limited = run_design(lim.plant, lim.problem, show_progress=False, log=lambda m: None)
    from threadpoolctl import threadpool_limits
    with threadpool_limits(limits=1):
        res['compute_mpc'] = compute_mpc(limited, lim.plant)

    print('\nmeasurement -> command round trip (wall clock, this machine); ratios against the bare')
    print('ping-pong with the same executor and the same pacing')
    print(f"{'':44s} {'p50':>11s} {'p99':>11s}  {'p50/ping':>8s} {'p99/ping':>8s}")
    rows = [('bare ping-pong, EventsExecutor', 'ping_pong_events', 'ping_pong_events'),
            ('bare ping-pong, EventsExecutor (again)', 'ping_pong_events_after', 'ping_pong_events'),
            ('plant <-> lqg lockstep, EventsExecutor', 'loop_lockstep_events', 'ping_pong_events'),
            ('bare ping-pong, SingleThreadedExecutor', 'ping_pong_single', 'ping_pong_single'),
            ('plant <-> lqg lockstep, SingleThreaded', 'loop_lockstep_single', 'ping_pong_single')]
    if not args.no_realtime:
        rows += [('bare ping-pong every 25 ms, Events', 'ping_pong_paced_events', 'ping_pong_paced_events'),
                 ('plant <-> lqg realtime rtf 10, Events', 'loop_realtime_rtf10_events', 'ping_pong_paced_events')]
    for name, key, base in rows:
        r, b = res[key], res[base]
        print(f"{name:44s} {fmt(r['p50']):>11s} {fmt(r['p99']):>11s}  "
              f"{r['p50'] / b['p50']:8.2f} {r['p99'] / b['p99']:8.2f}")
    for key in [k for k in res if k.startswith('loop_')]:
        print(f"  {key}: deadline misses {res[key]['deadline_misses']}, max {fmt(res[key]['max'])}")
    cp = res['compute']
    print('\nper-step compute of estimator + LQR (pure calls; reference design, n_r = '
          f'{design.n_r}, n_x = {design.info.n_x})')
    print(f"{'':52s} {'mean':>11s} {'p50':>11s} {'p99':>11s}")
    for label, key in (('KF update + LQR law + KF predict, BLAS 1 thread', ('blas_1', 'core')),
                       ('KF update + LQR law + KF predict, BLAS default', ('blas_default', 'core')),
                       ('+ field reconstruction and messages, BLAS 1', ('blas_1', 'node')),
                       ('+ field reconstruction and messages, BLAS default', ('blas_default', 'node'))):
        r = cp[key[0]][key[1]]
        print(f"{label:52s} {fmt(r['mean']):>11s} {fmt(r['p50']):>11s} {fmt(r['p99']):>11s}")
    print(f"  thread pools: {', '.join(cp['pools'])}")
    mp = res['compute_mpc']
    print(f"\nfeedback law per step on closed-loop estimates (design with u in [{mp['limits'][0]:g}, "
          f"{mp['limits'][1]:g}], n_r = {mp['n_r']}, MPC horizon {mp['horizon']}, BLAS 1 thread; "
          f"{100 * mp['qp_share']:.0f} % of the MPC's steps solve a QP, {mp['fallbacks']} fallbacks)")
    print(f"{'':52s} {'mean':>11s} {'p50':>11s} {'p99':>11s}")
    for label, key in (('LQR law, clipped', 'lqr'), ('MPC, every step', 'mpc_all'),
                       ('MPC, steps with no active limit (no QP)', 'mpc_free'), ('MPC, steps solving the QP (OSQP)', 'mpc_qp')):
        r = mp[key]
        print(f"{label:52s} {fmt(r['mean']):>11s} {fmt(r['p50']):>11s} {fmt(r['p99']):>11s}")
    ratio = res['loop_lockstep_events']['p50'] / res['ping_pong_events']['p50']
    print(f"\ntarget round trip <= 1.5x ping-pong: lockstep p50 ratio {ratio:.2f} -> "
          f"{'met' if ratio <= 1.5 else 'NOT met'}; target compute < 50 us: "
          f"{fmt(cp['blas_1']['core']['p50'])} -> {'met' if cp['blas_1']['core']['p50'] < 50e-6 else 'NOT met'}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
