"""Shared pieces of the offline command-line tools (design, evaluate, validate)."""
from __future__ import annotations

import argparse
import contextlib
import sys
from typing import NoReturn

from sep_estimator.design_file import Design, DesignFileError, load_design
from sep_plant.protocol import PlantError
from sep_plant.scenario import Scenario, ScenarioError, load_scenario


class Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Show defaults and keep the description's line breaks."""


def fail(message: str, code: int = 2) -> NoReturn:
    """Print `error: message` to stderr and exit non-zero (no traceback)."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(code)


def add_threads(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--threads", type=int, default=1,
                        help="BLAS threads. The work is many small matrices where extra threads "
                             "oversubscribe the cores (see bench/); raise it on a big grid")


def add_memory_budget(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--memory-budget", metavar="SIZE", default=None,
                        help="memory for one batch of runs (experiments, Monte Carlo), e.g. 2G or 512M; "
                             "larger batches are split; None: a quarter of the free memory")


def add_device(parser: argparse.ArgumentParser) -> None:
    from sep_plant.device import DEVICES

    parser.add_argument("--device", choices=DEVICES, default="cpu",
                        help="where the plant's batched steps run: cpu (numpy) or cuda (CuPy on an NVIDIA GPU: the "
                             "steps of the experiments, the EnKF, the rollouts and the Monte Carlo; the design's own "
                             "work stays on the CPU; on --dask each worker steps on its current CUDA device, one GPU "
                             "per worker via CUDA_VISIBLE_DEVICES or dask-cuda). Needs CuPy and a device-capable "
                             "plant (the built-in ones); results equal the CPU's to round-off")


def add_dask(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dask", metavar="WHERE", default=None,
                        help="run the experiment and Monte Carlo batches on Dask: local (a LocalCluster, one "
                             "worker process per core, one thread each), local:N (N workers) or "
                             "tcp://HOST:PORT (a running scheduler; see README). Same results as in-process")


@contextlib.contextmanager
def engine_or_exit(text: str | None, log=None):
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
        fail(str(exc), code=1)
    finally:
        engine.close()


def memory_budget_or_exit(text: str | None) -> int | None:
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


def plant_or_exit(scenario: Scenario, where: str = "scenario", device: str = "cpu"):
    """Build and check the scenario's plant (exit 2 with the plant's problems), stepping on
    `device` (`sep_plant.device`; exit 2 when it is not available or the plant cannot go there)."""
    from sep_plant.conformance import check_plant
    from sep_plant.device import DeviceError, on_device

    try:
        plant = scenario.plant
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
