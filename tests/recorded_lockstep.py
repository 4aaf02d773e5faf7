"""A recorded lockstep episode: `record` + `lqg` + `plant` as module processes of this tree.

Shared by the end-to-end recording tests: the recorder and the lqg start first, the plant waits
for both (lockstep), and every process must exit by itself after the final step.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SRC = os.pathsep.join(str(REPO / p) for p in ("sep_plant", "sep_estimator", "sep_control"))


def popen(args: list[str], cwd: Path, name: str) -> subprocess.Popen:
    """`python -m ARGS` in `cwd` with this tree's packages first; output to `cwd/NAME.log`."""
    env = dict(os.environ, PYTHONPATH=SRC + os.pathsep + os.environ.get("PYTHONPATH", ""), PYTHONUNBUFFERED="1")
    log = open(cwd / f"{name}.log", "w")
    return subprocess.Popen([sys.executable, "-m", *args], cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL)


def log_of(cwd: Path, name: str) -> str:
    return (cwd / f"{name}.log").read_text()


def run_recorded_episode(cwd: Path, design_path: Path, scenario: Path, seed: int, run: int, procs: list,
                         plant_params: tuple[str, ...] = ()) -> None:
    """Record one lockstep episode into `cwd/bag`; the plant writes `cwd/traj.npz`.
    `plant_params`: further `-p NAME:=VALUE` values of the plant node."""
    rec = popen(["sep_control.ros.record_node", "--out", "bag", "--final-grace", "0.5", "--ready-file", "ready",
                 "--ready-topics", "command", "state_estimate", "field_estimate", "--max-duration", "120"],
                cwd, "record")
    procs.append(rec)
    lqg = popen(["sep_control.ros.lqg_node", "--ros-args", "-p", f"design_file:={design_path}"], cwd, "lqg")
    procs.append(lqg)
    t0 = time.monotonic()
    while not (cwd / "ready").exists():
        assert time.monotonic() - t0 < 60, log_of(cwd, "record") + log_of(cwd, "lqg")
        assert rec.poll() is None and lqg.poll() is None, log_of(cwd, "record") + log_of(cwd, "lqg")
        time.sleep(0.05)
    extra = [a for p in plant_params for a in ("-p", p)]
    plant = popen(["sep_plant.ros.plant_node", "--ros-args", "-p", f"scenario_file:={scenario}", "-p", f"seed:={seed}",
                   "-p", f"run:={run}", "-p", "wait_for_subscribers:=2", "-p", "wait_for_field_subscribers:=1",
                   "-p", "trajectory_file:=traj.npz", *extra], cwd, "plant")
    procs.append(plant)
    assert plant.wait(120) == 0, log_of(cwd, "plant")
    assert rec.wait(60) == 0, log_of(cwd, "record")     # stops by itself after the final step
    assert "episode ended" in log_of(cwd, "record")
    lqg.wait(30)
