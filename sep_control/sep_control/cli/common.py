"""Shared pieces of the `sep` subcommands: the error style, option groups, deprecated
spellings, the compute options (--threads, --memory-budget, --dask, --device) and the loaders
that exit with a message instead of a traceback.

Errors: ``sep <subcommand>: error: <message>`` on stderr, exit 2 for bad input and 1 for a task
that failed (`fail`); argparse's own errors look the same (its prog is ``sep <subcommand>``).
Deprecated spellings still work and print one ``sep <subcommand>: warning: ...`` line.
"""
from __future__ import annotations

import argparse
import contextlib
import sys
from typing import Any, Callable, NoReturn

from sep_estimator.design import Design
from sep_estimator.design_file import DesignFileError, load_design
from sep_plant.protocol import PlantError
from sep_plant.scenario import Scenario, ScenarioError, load_scenario

from sep_control.control.controllers import CONTROLLER_ALIASES  # old controller names, accepted with a warning

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2

_prog = ["sep"]


class Formatter(argparse.RawDescriptionHelpFormatter):
    """Keep the description's line breaks; add "(default: X)" to an option's help unless it says
    its default itself or has none worth saying (None, a switch that is off)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        switch = isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction))
        if "default" in text or switch or action.default is None or action.default == argparse.SUPPRESS \
                or not action.option_strings:
            return text
        return text + " (default: %(default)s)"


def set_prog(prog: str) -> None:
    """The name messages start with (``sep design``), set by `sep_control.cli.main` per subcommand."""
    _prog[0] = prog


def fail(message: str, code: int = EXIT_BAD_INPUT) -> NoReturn:
    """Print ``sep <subcommand>: error: message`` to stderr and exit with `code` (2: bad input,
    1: a task failed); no traceback."""
    print(f"{_prog[0]}: error: {message}", file=sys.stderr)
    sys.exit(code)


def warn(message: str) -> None:
    """One ``sep <subcommand>: warning: message`` line on stderr."""
    print(f"{_prog[0]}: warning: {message}", file=sys.stderr)


def legacy_main(name: str, argv: list[str] | None) -> int:
    """The old console script `name` (design, evaluate, ...): one deprecation line, then
    ``sep name argv``."""
    from sep_control.cli.main import main

    print(f"{name}: warning: the `{name}` command is deprecated; use `sep {name}`", file=sys.stderr)
    return main([name, *(sys.argv[1:] if argv is None else argv)])


def groups(parser: argparse.ArgumentParser) -> tuple[argparse._ArgumentGroup, argparse._ArgumentGroup]:
    """The subcommand's "Basic" and "Advanced" option groups."""
    return parser.add_argument_group("Basic"), parser.add_argument_group("Advanced")


class _Deprecated(argparse.Action):
    """An old flag: stores into the new one's dest and warns once."""

    def __init__(self, option_strings, dest, new: str = "", **kw):
        self.new = new
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        warn(f"{option_string} is deprecated; use {self.new}")
        setattr(namespace, self.dest, values)


def add_deprecated(group, old: str, new: str, dest: str, **kw: Any) -> None:
    """Accept the old flag `old` for `new` (same `dest`), hidden from --help."""
    group.add_argument(old, dest=dest, action=_Deprecated, new=new, help=argparse.SUPPRESS,
                       default=argparse.SUPPRESS, **kw)


def controller_name(text: str) -> str:
    """A --controller(s) value as given, or the new name of an old one (`lqr`, `mpc`) with a warning."""
    if text in CONTROLLER_ALIASES:
        warn(f"controller {text!r} is deprecated; use {CONTROLLER_ALIASES[text]!r}")
        return CONTROLLER_ALIASES[text]
    return text


def add_compute_options(group, *, memory_budget: bool = True, dask: bool = True, device: bool = True) -> None:
    """--threads, --memory-budget, --dask, --device (where the work runs; none changes a result
    beyond round-off) into `group` (the subcommand's "Advanced" group)."""
    group.add_argument("--threads", type=int, default=1,
                       help="BLAS threads. The work is many small matrices where extra threads oversubscribe "
                            "the cores (see bench/); raise it on a big grid")
    if memory_budget:
        group.add_argument("--memory-budget", metavar="SIZE", default=None,
                           help="memory for one batch of runs (experiments, Monte Carlo), e.g. 2G or 512M; "
                                "larger batches are split; None: a quarter of the free memory")
    if dask:
        group.add_argument("--dask", metavar="WHERE", default=None,
                           help="run the batches of runs on Dask: local (a LocalCluster, one worker process per "
                                "core, one thread each), local:N (N workers) or tcp://HOST:PORT (a running "
                                "scheduler; see docs/cluster.md). Same results as in-process")
    if device:
        from sep_plant.device import DEVICES

        group.add_argument("--device", choices=DEVICES, default="cpu",
                           help="where the plant's batched steps run: cpu (numpy) or cuda (CuPy on an NVIDIA GPU; "
                                "the design's own work stays on the CPU; on --dask each worker steps on its "
                                "current CUDA device). Needs CuPy and a device-capable plant (the built-in ones); "
                                "results equal the CPU's to round-off (docs/gpu.md)")


@contextlib.contextmanager
def engine_or_exit(text: str | None, log: Callable[[str], None] | None = None):
    """The engine of a --dask value (exit 2 when the value is bad or the scheduler unreachable);
    a task that fails on it exits 1 with the task's name and the worker's error."""
    from sep_control.compute.engine import EngineError, TaskError, open_engine

    try:
        engine = open_engine(text, log=log)
    except EngineError as exc:
        fail(str(exc))
    try:
        yield engine
    except TaskError as exc:
        fail(str(exc), code=EXIT_FAILED)
    finally:
        engine.close()


def memory_budget_or_exit(text: str | None) -> int | None:
    """Bytes of a --memory-budget value (None: the default); exit 2 when unreadable."""
    if text is None:
        return None
    from sep_control.compute.budget import parse_budget

    try:
        return parse_budget(text)
    except ValueError as exc:
        fail(str(exc))


def blas_threads(n: int):
    """Context manager limiting BLAS threads (threadpoolctl)."""
    from threadpoolctl import threadpool_limits

    if n < 1:
        fail(f"--threads must be >= 1, got {n}")
    return threadpool_limits(limits=n)


def scenario_or_exit(path: str | None) -> Scenario:
    try:
        return load_scenario(path)
    except ScenarioError as exc:
        fail(f"{exc}")


def design_or_exit(path: str, scenario: Scenario | None = None) -> Design:
    try:
        return load_design(path, scenario)
    except DesignFileError as exc:
        fail(f"{exc}")


def plant_or_exit(scenario: Scenario, where: str = "scenario", device: str = "cpu", plant: Any = None):
    """Build and check the scenario's plant (exit 2 with the plant's problems), stepping on
    `device` (`sep_plant.device`; exit 2 when it is not available or the plant cannot go there).
    `plant`: check this plant object instead (a truth plant), with the scenario's problem."""
    from sep_plant.conformance import check_plant
    from sep_plant.device import DeviceError, on_device

    try:
        plant = scenario.plant if plant is None else plant
        check_plant(plant, scenario.problem.channels("u_init", int(plant.n_u)), name=scenario.plant_type)
    except (ScenarioError, PlantError) as exc:
        fail(f"{where}: {exc}")
    try:
        plant = on_device(plant, device)
    except DeviceError as exc:
        fail(str(exc))
    if device != "cpu":                     # the device's step too: a plant may break only there
        try:
            check_plant(plant, scenario.problem.channels("u_init", int(plant.n_u)), name=scenario.plant_type)
        except PlantError as exc:
            fail(f"{where}, on --device {device}: {exc}")
    return plant


def stderr_log(quiet: bool = False) -> Callable[[str], None]:
    """A log function writing lines to stderr (when `quiet`, only the lines that start with
    "warning:": a quiet run still says what the user should act on)."""
    if quiet:
        return lambda msg: print(msg, file=sys.stderr) if msg.startswith("warning:") else None
    return lambda msg: print(msg, file=sys.stderr)
