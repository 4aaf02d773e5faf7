"""`sep demo`: the main job. Design (or reuse a design file made from the same inputs), run plant +
lqg over ROS 2 topics for one full episode (lockstep, faster than real time, by default), record
a bag, and print the closed-loop metrics of the episode (metrics (docs/method.md); ``--json PATH``
too) and where the report is.

The nodes run as separate processes from the install space, resolved like `ros2 run` does
(ament index: <prefix>/lib/<pkg>/<exe>; build and source the workspace first, `make demo`
does both), on an isolated ROS_DOMAIN_ID with localhost-only discovery. Every child process
is stopped on exit, Ctrl-C or error. This module imports no ROS package itself.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import sys
import time
from pathlib import Path

from sep_plant import topics as T
from sep_plant.noise import DEFAULT_SEED

from sep_control.cli.common import (EXIT_FAILED, EXIT_OK, add_compute_options, add_deprecated, controller_name, fail,
                                    groups, legacy_main, plant_or_exit, scenario_or_exit)
from sep_control.cli.design import (add_design_options, make_design, recorded_settings, settings_fit_or_exit,
                                   settings_from_args)
from sep_control.cli.demo_report import episode_metrics, print_metrics, run_analysis
from sep_control.cli.processes import Children, executable
from sep_control.compute.progress import bars_wanted
from sep_control.control.controllers import NODE_CONTROLLERS

#: the controllers' output topics the recorder must have matched before the plant starts, and how long
#: the demo waits for that
CONTROLLER_TOPICS = (T.COMMAND, T.STATE_ESTIMATE, T.FIELD_ESTIMATE)
RECORDER_READY_S = 30.0


def _appears(path: Path, timeout: float) -> bool:
    """Whether `path` exists within `timeout` seconds (polled)."""
    end = time.monotonic() + timeout
    while not path.exists():
        if time.monotonic() > end:
            return False
        time.sleep(0.05)
    return True


HELP = "design (or reuse), run plant + controller over ROS 2 topics, record and report one episode"
DESCRIPTION = __doc__.split("\n\n")[0] + """

A design file is reused only when it was made from the same plant (type, keys, files), problem
and design settings as this run's (its source record's SHA-256); otherwise what differs is
printed and the design runs again. The design options below are `sep design`'s.

Example:  sep demo --out out/demo --scenario sep_plant/scenarios/plate.yaml
"""



def log(msg: str) -> None:
    print(f'[demo] {msg}', flush=True)


def configure(parser: argparse.ArgumentParser) -> None:
    """The options of `sep demo`."""
    basic, advanced = groups(parser)
    basic.add_argument('--out', default='out/demo', metavar='DIR', help='output folder')
    basic.add_argument('--scenario', metavar='FILE', help='scenario YAML (default: the reference scenario)')
    basic.add_argument('--design', metavar='FILE', help='design file to use/write (default DIR/design.npz)')
    basic.add_argument('--redesign', action='store_true',
                       help='run the design even if the design file was made from the same inputs')
    basic.add_argument('--controller', choices=NODE_CONTROLLERS, type=controller_name, default='rom_lqg',
                       help='feedback law: rom_lqg (TV-LQR on the ROM estimate, commands clipped to the limits) or '
                            'rom_mpc (box-constrained MPC on the ROM)')
    basic.add_argument('--mode', choices=('lockstep', 'realtime'), default='lockstep',
                       help='plant mode (lockstep: as fast as the controller answers)')
    basic.add_argument('--real-time-factor', type=float, default=10.0, metavar='RTF',
                       help='realtime: simulated seconds per wall second')
    add_deprecated(advanced, '--rtf', '--real-time-factor', 'real_time_factor', type=float)
    basic.add_argument('--seed', type=int, default=DEFAULT_SEED, help='noise seed (a Monte Carlo seed)')
    basic.add_argument('--run', type=int, default=0, help='run index within the seed')
    basic.add_argument('--record', dest='record', action='store_true', default=None,
                       help='record a rosbag2 bag and write its report (default when `record` is installed)')
    basic.add_argument('--no-record', dest='record', action='store_false', help='do not record')
    basic.add_argument('--json', metavar='PATH', help='write the episode metrics as JSON (docs/method.md)')
    advanced.add_argument('--three', action='store_true', help='run estimator and lqr as two processes instead of lqg')
    advanced.add_argument('--domain-id', type=int, help='ROS_DOMAIN_ID (default: a random free-ish id in 1..101)')
    advanced.add_argument('--timeout', type=float, default=600.0, help='give up after this many seconds')
    add_design_options(advanced, advanced)
    add_compute_options(advanced)


def run(args: argparse.Namespace) -> int:
    return DemoRun(args).run()


def reusable_design(path: Path, scenario, settings):
    """The design in `path` when it was made from `scenario` and `settings` (the SHA-256 of its
    source record matches), else None; says which, and what differs, on stdout."""
    from sep_estimator.design_file import DesignFileError, load_design
    from sep_estimator.design_source import source_differences

    try:
        d = load_design(path)
    except DesignFileError as exc:
        log(f'existing design file not usable ({exc}); redesigning')
        return None
    diff = source_differences(d, scenario, recorded_settings(settings, scenario.plant, scenario.problem.n_steps))
    if diff:
        log(f'design file {path} was made from other inputs; redesigning. Design file != now:\n    '
            + '\n    '.join(diff))
        return None
    log(f'reusing design file {path} (made from the same plant, problem and settings; --redesign to recompute)')
    return d


class DemoRun:
    """One demo: its scenario, output folder and executables, checked on construction (exit 2
    with what to fix); `run` designs or reuses, runs the episode and reports it."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.scenario = scenario_or_exit(args.scenario)
        self.plant = plant_or_exit(self.scenario, args.scenario or 'reference scenario')   # checked, on the CPU
        self.out = Path(args.out).resolve()
        self.out.mkdir(parents=True, exist_ok=True)
        self.exes = {name: executable(pkg, name) for pkg, name in
                     (('sep_plant', 'plant'), ('sep_control', 'lqg'), ('sep_estimator', 'estimator'),
                      ('sep_control', 'lqr'), ('sep_control', 'record'))}
        self.controllers = ['estimator', 'lqr'] if args.three else ['lqg']
        missing = [n for n in ['plant'] + self.controllers if self.exes[n] is None]
        if missing:
            fail(f'executables {missing} not found in the ament index (AMENT_PREFIX_PATH); build and source the '
                 'workspace first: `make build && . ros_ws/install/setup.sh` (or `make demo`)')
        self.record = self.exes['record'] is not None if args.record is None else args.record
        if self.record and self.exes['record'] is None:
            fail('--record given but the `record` executable is not installed')
        self.files = {k: self.out / f'{k}.json' for k in ('plant', 'lqg', 'estimator', 'lqr')}
        self.traj, self.bag = self.out / 'trajectory.npz', self.out / 'bag'

    # ------------------------------------------------------------------ design
    def design(self):
        """(design, its file): the file at --design (default DIR/design.npz) when it was made from
        this run's inputs, else a new design written there."""
        from sep_estimator.design_file import save_design

        args, scenario = self.args, self.scenario
        path = Path(args.design) if args.design else self.out / 'design.npz'
        settings = settings_from_args(args, scenario)
        if path.is_file() and not args.redesign:
            d = reusable_design(path, scenario, settings)
            if d is not None:
                return d, path
        plant = (self.plant if args.device == 'cpu' else
                 plant_or_exit(scenario, args.scenario or 'reference scenario', device=args.device))
        settings_fit_or_exit(settings, plant)
        log(f'designing for {args.scenario or "the reference scenario"} (plant {scenario.plant_type}, '
            f'n_x={plant.n_x}, N={scenario.problem.n_steps}) ...')
        t0 = time.perf_counter()
        d = make_design(plant, scenario, settings, args, log=lambda m: log('  ' + m), show_progress=bars_wanted())
        save_design(path, d)
        log(f'design written to {path} in {time.perf_counter() - t0:.1f} s')
        return d, path

    # ----------------------------------------------------------------- episode
    def run(self) -> int:
        design, design_file = self.design()
        env = dict(os.environ)
        env['ROS_DOMAIN_ID'] = str(self.args.domain_id if self.args.domain_id is not None else random.randint(1, 101))
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        env.pop('ROS_LOCALHOST_ONLY', None)
        logs = self.out / 'logs'
        logs.mkdir(exist_ok=True)
        kids = Children(logs, env)
        for f in list(self.files.values()) + [self.traj]:
            f.unlink(missing_ok=True)
        log(f'ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]} (localhost only); logs in {logs}')
        # SIGTERM behaves like Ctrl-C: children are always stopped in `finally`
        signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
        try:
            self.start_nodes(kids, design, design_file)
            t0 = time.perf_counter()
            kids.start('plant', self.plant_argv())
            if not self.episode_ended(kids):
                return EXIT_FAILED
            self.report(kids, design, design_file, time.perf_counter() - t0)
            return EXIT_OK
        except KeyboardInterrupt:
            kids.dump_stacks(0.5)
            log(f'interrupted; stopping the nodes. Their logs (with their stacks now) end:\n{kids.tails(40)}')
            return 130
        finally:
            kids.stop_all()

    def start_nodes(self, kids: Children, design, design_file: Path) -> None:
        """The recorder (if recording) and the controller node(s), before the plant; with a
        recorder, returns once it has matched the controllers' output topics (the plant's wait
        for subscribers covers only its own topics, and a lockstep episode can end before a late
        match: a bag without the controllers' topics)."""
        args, files = self.args, self.files
        ready = kids.log_dir / 'record.ready'
        if self.record:
            if self.bag.exists():
                shutil.rmtree(self.bag)
            ready.unlink(missing_ok=True)
            kids.start('record', [self.exes['record'], '--out', str(self.bag), '--ready-file', str(ready),
                                  '--ready-topics', *CONTROLLER_TOPICS])
        ctl = ['--ros-args', '-p', f'design_file:={design_file}',
               '-p', f'controller:={args.controller}']
        if args.three:
            kids.start('estimator', [self.exes['estimator'], '--ros-args', '-p', f'design_file:={design_file}',
                                     '-p', f'summary_file:={files["estimator"]}'])
            timeout = 0.4 * design.info.dt / args.real_time_factor if args.mode == 'realtime' else 0.5
            kids.start('lqr', [self.exes['lqr'], *ctl, '-p', f'summary_file:={files["lqr"]}',
                               '-p', f'estimate_timeout_s:={timeout}'])
        else:
            kids.start('lqg', [self.exes['lqg'], *ctl, '-p', f'summary_file:={files["lqg"]}'])
        if self.record and not _appears(ready, RECORDER_READY_S):
            log(f'warning: the recorder matched the controllers\' topics not within {RECORDER_READY_S:g} s; '
                f'starting the episode anyway (the bag may miss their first messages)')
        log(f'running plant ({args.mode}'
            + (f', real_time_factor {args.real_time_factor:g}' if args.mode == 'realtime' else '')
            + f', seed {args.seed} run {args.run}) + ' + ' + '.join(self.controllers)
            + (' + record' if self.record else '')
            + f' for {design.n_steps} steps ({design.n_steps * design.info.dt:g} s simulated)')

    def plant_argv(self) -> list[str]:
        args = self.args
        argv = [self.exes['plant'], '--ros-args', '-p', f'mode:={args.mode}',
                '-p', f'real_time_factor:={args.real_time_factor}', '-p', f'seed:={args.seed}',
                '-p', f'run:={args.run}', '-p', f'summary_file:={self.files["plant"]}',
                '-p', f'trajectory_file:={self.traj}',
                # estimator (+ lqr's watchdog) (+ recorder) must hear step 0
                '-p', f'wait_for_subscribers:={len(self.controllers) + (1 if self.record else 0)}',
                '-p', f'wait_for_field_subscribers:={1 if self.record else 0}']
        if args.scenario:
            argv += ['-p', f'scenario_file:={Path(args.scenario).resolve()}']
        return argv

    def episode_ended(self, kids: Children) -> bool:
        """Wait for the plant's last step and the controllers' exits; False (with the nodes' log
        tails printed) when one failed or --timeout passed."""
        prc = kids.wait('plant', self.args.timeout)
        if prc is None:
            kids.dump_stacks()
            log(f'the plant has not finished after --timeout {self.args.timeout:g} s; stopping the nodes. '
                f'Their logs (with their stacks now) end:\n{kids.tails(60)}')
            return False
        if prc != 0:
            log(f'plant failed (exit {prc}):\n{kids.tails()}')
            return False
        for name in self.controllers:
            if kids.wait(name, 30) != 0:
                log(f'{name} failed (exit {kids.procs[name].returncode}):\n{kids.tail(name)}')
                return False
        if self.record and kids.wait('record', 15) is None:
            kids.stop('record')
        return True

    def report(self, kids: Children, design, design_file: Path, wall: float) -> None:
        """The episode's metrics (and the bag's report) printed, and written with --json."""
        m = episode_metrics(design, self.traj, self.files, self.args.three)
        m['total_wall_s'] = wall
        report = None
        if self.record and self.bag.exists():
            report, bag_metrics = run_analysis(kids, self.bag, design_file, self.out, log)
            for key in ('coverage_2sigma', 'latency_p50_s', 'latency_p99_s'):   # measured on the bag
                if bag_metrics.get(key) is not None:
                    m[key] = bag_metrics[key]
        print_metrics(m, design, self.args.controller)
        if self.args.json:
            Path(self.args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(self.args.json).write_text(json.dumps(m, indent=2) + '\n')
            log(f'metrics JSON: {self.args.json}')
        if self.record:
            log(f'bag: {self.bag}')
        if report:
            log(f'report: {report}')


def main(argv: list[str] | None = None) -> int:
    """The old `demo` command: `sep demo` with a deprecation line."""
    return legacy_main('demo', argv)


if __name__ == '__main__':
    sys.exit(main())
