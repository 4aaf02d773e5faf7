"""`demo`: the main job. Design (or reuse a matching design file), run plant + lqg over ROS 2
topics for one full episode (lockstep, faster than real time, by default), record a bag, and
print the closed-loop metrics of the episode (metrics (docs/method.md); ``--json PATH`` too) and
where the report is.

The nodes run as separate processes from the install space, resolved like `ros2 run` does
(ament index: <prefix>/lib/<pkg>/<exe>; build and source the workspace first, `make demo`
does both), on an isolated ROS_DOMAIN_ID with localhost-only discovery.  Every child process
is stopped on exit, Ctrl-C or error.

    demo [--out DIR] [--scenario FILE] [--redesign] [--mode lockstep|realtime] [--rtf 10]
         [--seed S] [--run I] [--record|--no-record] [--json PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2


def executable(pkg: str, exe: str) -> str | None:
    """ros2run's lookup: <prefix of pkg in the ament index>/lib/<pkg>/<exe>, or None."""
    try:
        from ament_index_python import PackageNotFoundError, get_package_prefix
        prefix = get_package_prefix(pkg)
    except (ImportError, LookupError, Exception):  # noqa: BLE001 - PackageNotFoundError et al.
        return None
    path = Path(prefix) / 'lib' / pkg / exe
    return str(path) if path.is_file() and os.access(path, os.X_OK) else None


class Children:
    """Child processes, each in its own process group; `stop_all` always reaps them."""

    def __init__(self, log_dir: Path, env: dict):
        self.log_dir, self.env = log_dir, env
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}

    def start(self, name: str, argv: list[str]) -> subprocess.Popen:
        log = self.log_dir / f'{name}.log'
        fh = open(log, 'wb')
        p = subprocess.Popen(argv, env=self.env, stdout=fh, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL, start_new_session=True)
        fh.close()
        self.procs[name], self.logs[name] = p, log
        return p

    def wait(self, name: str, timeout: float | None) -> int | None:
        try:
            return self.procs[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def stop(self, name: str, grace: float = 5.0) -> int | None:
        p = self.procs[name]
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGINT)
                p.wait(timeout=grace)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait(timeout=10)
        return p.returncode

    def stop_all(self) -> None:
        for name in reversed(list(self.procs)):
            self.stop(name, grace=3.0)

    def dump_stacks(self, settle_s: float = 1.0) -> None:
        """Ask every running child for its Python stacks (SIGUSR1: the nodes' faulthandler writes
        them to their logs and they go on), so that the log tails show where each one is."""
        running = [p for p in self.procs.values() if p.poll() is None]
        for p in running:
            try:
                os.kill(p.pid, signal.SIGUSR1)
            except (ProcessLookupError, PermissionError):
                pass
        if running:
            time.sleep(settle_s)

    def tails(self, n: int = 15) -> str:
        """The last lines of every child's log (what a failure report needs)."""
        return '\n'.join(f'--- {name} ({"running" if p.poll() is None else f"exit {p.returncode}"}), '
                         f'{self.logs[name]}:\n{self.tail(name, n)}' for name, p in self.procs.items())

    def tail(self, name: str, n: int = 15) -> str:
        try:
            return '\n'.join(self.logs[name].read_text(errors='replace').splitlines()[-n:])
        except OSError:
            return ''


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='demo', description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--out', default='out/demo', metavar='DIR', help='output folder (default out/demo)')
    p.add_argument('--scenario', metavar='FILE', help='scenario YAML (default: the reference scenario)')
    p.add_argument('--design', metavar='FILE', help='design file to use/write (default DIR/design.npz)')
    p.add_argument('--redesign', action='store_true', help='run the design even if a matching design file exists')
    p.add_argument('--controller', choices=('lqr', 'mpc'), default='lqr',
                   help='feedback law: lqr (TV-LQR, commands clipped to the limits) or mpc (box-constrained '
                        'MPC on the ROM)')
    p.add_argument('--mode', choices=('lockstep', 'realtime'), default='lockstep',
                   help='plant mode (default lockstep: as fast as the controller answers)')
    p.add_argument('--rtf', type=float, default=10.0, help='realtime: real-time factor (default 10)')
    p.add_argument('--seed', type=int, default=0, help='noise seed (default 0)')
    p.add_argument('--run', type=int, default=0, help='run index within the seed (default 0)')
    p.add_argument('--record', dest='record', action='store_true', default=None,
                   help='record a rosbag2 bag and write its report (default when `record` is installed)')
    p.add_argument('--no-record', dest='record', action='store_false', help='do not record')
    p.add_argument('--three', action='store_true', help='run estimator and lqr as two processes instead of lqg')
    p.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: a random free-ish id in 1..101)')
    p.add_argument('--timeout', type=float, default=600.0, help='give up after this many seconds')
    p.add_argument('--json', metavar='PATH', help='write the episode metrics as JSON (metrics (docs/method.md))')
    return p


def log(msg: str) -> None:
    print(f'[demo] {msg}', flush=True)


def get_design(args, scenario, out: Path):
    from sep_estimator.design_file import DesignFileError, load_design, save_design

    path = Path(args.design) if args.design else out / 'design.npz'
    if path.is_file() and not args.redesign:
        try:
            d = load_design(path, expect_scenario=scenario)
            log(f'reusing design file {path} (matches the scenario; --redesign to recompute)')
            return d, path
        except DesignFileError as exc:
            log(f'existing design file not usable ({exc}); redesigning')
    from sep_control.design.pipeline import DesignSettings, run_design
    plant = scenario.plant
    log(f'designing for {args.scenario or "the reference scenario"} (plant {scenario.plant_type}, '
        f'n_x={plant.n_x}, N={scenario.problem.n_steps}) ...')
    t0 = time.perf_counter()
    d = run_design(plant, scenario.problem, DesignSettings.for_scenario(scenario), show_progress=sys.stderr.isatty(),
                   log=lambda m: log('  ' + m))
    save_design(path, d)
    log(f'design written to {path} in {time.perf_counter() - t0:.1f} s')
    return d, path


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from sep_plant.conformance import check_plant
    from sep_plant.protocol import PlantError
    from sep_plant.scenario import ScenarioError, load_scenario
    try:
        scenario = load_scenario(args.scenario)
        check_plant(scenario.plant, scenario.problem.channels('u_init', int(scenario.plant.n_u)),
                    name=scenario.plant_type)
    except (ScenarioError, PlantError) as exc:
        print(f'demo: {exc}', file=sys.stderr)
        return EXIT_USAGE
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    exes = {name: executable(pkg, name) for pkg, name in
            (('sep_plant', 'plant'), ('sep_control', 'lqg'), ('sep_estimator', 'estimator'),
             ('sep_control', 'lqr'), ('sep_control', 'record'), ('sep_control', 'analyze'))}
    need = ['plant'] + (['estimator', 'lqr'] if args.three else ['lqg'])
    missing = [n for n in need if exes[n] is None]
    if missing:
        print(f'demo: executables {missing} not found in the ament index (AMENT_PREFIX_PATH); build and '
              'source the workspace first: `make build && . ros_ws/install/setup.sh` (or `make demo`)',
              file=sys.stderr)
        return EXIT_USAGE
    record = exes['record'] is not None if args.record is None else args.record
    if record and exes['record'] is None:
        print('demo: --record given but the `record` executable is not installed', file=sys.stderr)
        return EXIT_USAGE

    design, design_file = get_design(args, scenario, out)
    scenario_file = Path(args.scenario).resolve() if args.scenario else None

    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(args.domain_id if args.domain_id is not None else random.randint(1, 101))
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env.pop('ROS_LOCALHOST_ONLY', None)
    logs = out / 'logs'
    logs.mkdir(exist_ok=True)
    kids = Children(logs, env)
    files = {k: out / f'{k}.json' for k in ('plant', 'lqg', 'estimator', 'lqr')}
    traj = out / 'trajectory.npz'
    for f in list(files.values()) + [traj]:
        f.unlink(missing_ok=True)
    bag = out / 'bag'
    log(f'ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]} (localhost only); logs in {logs}')
    rc = EXIT_FAIL
    # SIGTERM behaves like Ctrl-C: children are always stopped in `finally`
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    try:
        if record:
            if bag.exists():
                shutil.rmtree(bag)
            kids.start('record', [exes['record'], '--out', str(bag)])
        ctl = ['--ros-args', '-p', f'design_file:={design_file}']
        lqr_args = ['-p', f'controller:={args.controller}']
        if args.three:
            kids.start('estimator', [exes['estimator'], *ctl, '-p', f'summary_file:={files["estimator"]}'])
            timeout = 0.4 * design.info.dt / args.rtf if args.mode == 'realtime' else 0.5
            kids.start('lqr', [exes['lqr'], *ctl, *lqr_args, '-p', f'summary_file:={files["lqr"]}',
                               '-p', f'estimate_timeout_s:={timeout}'])
        else:
            kids.start('lqg', [exes['lqg'], *ctl, *lqr_args, '-p', f'summary_file:={files["lqg"]}'])
        plant_args = [exes['plant'], '--ros-args', '-p', f'mode:={args.mode}',
                      '-p', f'real_time_factor:={args.rtf}', '-p', f'seed:={args.seed}',
                      '-p', f'run:={args.run}', '-p', f'summary_file:={files["plant"]}',
                      '-p', f'trajectory_file:={traj}',
                      # estimator (+ lqr's watchdog) (+ recorder) must hear step 0
                      '-p', f'wait_for_subscribers:={(2 if args.three else 1) + (1 if record else 0)}',
                      '-p', f'wait_for_field_subscribers:={1 if record else 0}']
        if scenario_file:
            plant_args += ['-p', f'scenario_file:={scenario_file}']
        log(f'running plant ({args.mode}' + (f', real_time_factor {args.rtf:g}' if args.mode == 'realtime' else '')
            + f', seed {args.seed} run {args.run}) + ' + ('estimator + lqr' if args.three else 'lqg')
            + (' + record' if record else '') + f' for {design.n_steps} steps '
            f'({design.n_steps * design.info.dt:g} s simulated)')
        t0 = time.perf_counter()
        kids.start('plant', plant_args)
        prc = kids.wait('plant', args.timeout)
        wall = time.perf_counter() - t0
        if prc is None:
            kids.dump_stacks()
            log(f'the plant has not finished after --timeout {args.timeout:g} s; stopping the nodes. '
                f'Their logs (with their stacks now) end:\n{kids.tails(60)}')
            return EXIT_FAIL
        if prc != 0:
            log(f'plant failed (exit {prc}):\n{kids.tails()}')
            return EXIT_FAIL
        for name in (['estimator', 'lqr'] if args.three else ['lqg']):
            if kids.wait(name, 30) != 0:
                log(f'{name} failed (exit {kids.procs[name].returncode}):\n{kids.tail(name)}')
                return EXIT_FAIL
        if record and kids.wait('record', 15) is None:
            kids.stop('record')
        metrics_ = episode_metrics(design, traj, files, args.three)
        metrics_['total_wall_s'] = wall
        report = None
        if record and exes['analyze'] is not None and bag.exists():
            report, bag_metrics = run_analysis(kids, exes['analyze'], bag, design_file, out)
            if bag_metrics.get('coverage_2sigma') is not None:
                metrics_['coverage_2sigma'] = bag_metrics['coverage_2sigma']
        print_metrics(metrics_, design, 'rom_mpc' if args.controller == 'mpc' else 'rom_lqg')
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps(metrics_, indent=2) + '\n')
            log(f'metrics JSON: {args.json}')
        if record:
            log(f'bag: {bag}')
        if report:
            log(f'report: {report}')
        rc = EXIT_OK
    except KeyboardInterrupt:
        kids.dump_stacks(0.5)
        log(f'interrupted; stopping the nodes. Their logs (with their stacks now) end:\n{kids.tails(40)}')
        rc = 130
    finally:
        kids.stop_all()
    return rc


def episode_metrics(design, traj: Path, files: dict, three: bool) -> dict:
    import numpy as np

    from sep_control.evaluation import metrics as M
    z = np.load(traj, allow_pickle=False)
    F, U = z['F'], z['U']
    plant = json.loads(files['plant'].read_text())
    if three:
        est = json.loads(files['estimator'].read_text())
        lqr = json.loads(files['lqr'].read_text())
    else:
        both = json.loads(files['lqg'].read_text())
        est, lqr = both['estimator'], both['lqr']
    out = M.summarize(F[None], U[None], design.nominal.field, design.objective)
    out.update({'deadline_misses': plant['deadline_misses'],
                'rejected_messages': plant['rejected_messages'] + est['rejected_messages'] + lqr['rejected_messages'],
                'latency_p50_s': plant['latency_p50_s'], 'latency_p99_s': plant['latency_p99_s'],
                'lqr_fallbacks': lqr['fallbacks'], 'wall_s': plant['wall_s'], 'nis_mean': est.get('nis_mean'),
                'controller': lqr.get('controller', 'lqr'), 'mpc_fallbacks': lqr.get('mpc_fallbacks'),
                'mpc_qp_steps': lqr.get('mpc_qp_steps'), 'mpc_qp_p99_s': lqr.get('mpc_qp_p99_s'),
                'estimator_compute_p50_s': est.get('compute_p50_s'),
                'rejected_by_node': {'plant': plant.get('rejected_by_reason', {}),
                                     'estimator': est.get('rejected_by_reason', {}),
                                     'lqr': lqr.get('rejected_by_reason', {})}})
    return out


def run_analysis(kids: Children, analyze: str, bag: Path, design_file: Path, out: Path):
    report_dir = out / 'report'
    js = out / 'bag_metrics.json'
    js.unlink(missing_ok=True)
    kids.start('analyze', [analyze, str(bag), '--design', str(design_file), '--out', str(report_dir),
                           '--json', str(js)])
    if kids.wait('analyze', 120) != 0:
        log(f'analyze failed:\n{kids.tail("analyze")}')
        return None, {}
    try:
        data = json.loads(js.read_text())
    except (OSError, json.JSONDecodeError):
        data = {}
    if isinstance(data, list):
        data = data[0] if data else {}
    if isinstance(data, dict) and len(data) == 1 and isinstance(next(iter(data.values())), dict):
        data = next(iter(data.values()))
    report = next(iter(sorted(report_dir.glob('*.md'))), report_dir) if report_dir.exists() else None
    return report, data if isinstance(data, dict) else {}


def print_metrics(m: dict, design, name: str = 'rom_lqg') -> None:
    from sep_control.evaluation import metrics as M
    keys = [k for k in M.JSON_KEYS if k in m]
    info, obj = design.info, design.objective
    horizon = design.n_steps * info.dt
    k0, k1 = obj.window
    target = f'{obj.target[0]:g}' if (obj.target == obj.target[0]).all() else 'the target pattern'
    unit = f' {info.field_unit}' if info.field_unit else ''
    print()
    print(M.format_table({f'{name} (topics)': m}, keys))
    print(f"\nin band (whole field within {target} +- {obj.band:g}{unit} over t = {k0 * info.dt:g}..{k1 * info.dt:g} s): "
          f"{'yes' if m['in_band'] >= 1 else 'NO'}; episode {m['wall_s']:.2f} s wall for {horizon:g} s simulated "
          f"({horizon / m['wall_s']:.1f}x real time; {m['total_wall_s']:.1f} s with start-up); "
          f"LQR nominal fallbacks {m['lqr_fallbacks']}"
          + (f"; MPC: {m['mpc_qp_steps']} QPs (p99 {(m['mpc_qp_p99_s'] or 0) * 1e3:.2f} ms), "
             f"{m['mpc_fallbacks']} fallbacks to the clipped LQR" if m.get('controller') == 'mpc' else ''))


if __name__ == '__main__':
    sys.exit(main())
