"""The host (numpy) path of the design and the Monte Carlo is 0.8.0's, bit for bit.

The device-resident experiments (`sep_plant.device`, docs/gpu.md) route the design's per-step
work through an array module; with numpy that must be the very same operations. A coarse
reference design (default settings: sensitivity Jacobian, then TV-ERA, EnKF belief, gains,
field map) and a Monte Carlo through it are made twice, in subprocesses: with the sources of
release 0.8.0 (commit e10738f, extracted from this repository's history) and with this tree's.
Every array of the design files and every Monte Carlo metric must be equal (the metadata's
timings, creation time, source record and run-step counts aside)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tarfile
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
RELEASE = "e10738f"
PACKAGES = ("sep_plant", "sep_estimator", "sep_control")

SCRIPT = r"""
import json, sys
import numpy as np
from threadpoolctl import threadpool_limits
from sep_plant.scenario import load_scenario
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.evaluation.montecarlo import simulate
from sep_estimator.design_file import save_design

s = load_scenario(None).with_plant(n_x=40)
with threadpool_limits(1):
    # plan 0.8 (0.8.0's experiments) where the tree has plans; 0.8.0 itself has only that one
    plan = {"experiment_plan": "0.8"} if "experiment_plan" in DesignSettings.__dataclass_fields__ else {}
    d = run_design(s.plant, s.problem, DesignSettings(**plan), show_progress=False, log=lambda m: None)
    save_design(sys.argv[1], d)
    mc = simulate(s.plant, d, "rom_lqg", 3, 24)
np.savez(sys.argv[2], U=mc.U, Y=mc.Y, F=mc.F, F_hat=mc.F_hat)
print(json.dumps({k: v for k, v in mc.summary.items() if isinstance(v, (int, float))}))
"""


def _release_tree(dest: Path) -> Path | None:
    """The 0.8.0 packages' sources under dest (None: the commit is not in this repository)."""
    try:
        blob = subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", RELEASE, *PACKAGES],
                              capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    with tarfile.open(fileobj=BytesIO(blob)) as tar:
        tar.extractall(dest, filter="data")
    return dest


def _run(root: Path, out: Path) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join(str(root / p) for p in PACKAGES))
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(out / "d.npz"), str(out / "mc.npz")],
                          env=env, cwd=out, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _meta(npz) -> dict:
    meta = json.loads(npz["meta"].tobytes())
    meta.pop("timings", None)
    # Added or widened on purpose since 0.8.0 (CHANGELOG 0.9.0): the source record covers the sep
    # version and the plant's code, the design counts its run-steps, the format is version 5 (new
    # disturbance kinds and weighting keys). None of them enters an array.
    for key in ("source", "source_digest", "run_steps", "version"):
        meta.pop(key, None)
    meta.get("settings", {}).pop("experiment_plan", None)   # new setting; its "0.8" is 0.8.0's plan
    meta.get("settings", {}).pop("impulse_stride", None)    # new setting; plan 0.8's 1 is 0.8.0's experiments
    meta.get("settings", {}).pop("clip_correction", None)   # new setting; plan 0.8's off is 0.8.0's design
    # new setting; plan 0.8's tolerance is 0.8.0's
    assert meta.get("settings", {}).pop("field_tol", 1e-8) == 1e-8
    meta.get("provenance", {}).pop("created_unix", None)
    return meta


def test_the_host_path_is_the_releases_bit_for_bit(tmp_path):
    old = _release_tree(tmp_path / "release")
    if old is None:
        pytest.skip(f"commit {RELEASE} (release 0.8.0) is not in this repository's history")
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    ma = _run(old, tmp_path / "a")
    mb = _run(REPO, tmp_path / "b")
    assert ma == mb                                          # the Monte Carlo metrics, exactly
    with np.load(tmp_path / "a" / "d.npz") as a, np.load(tmp_path / "b" / "d.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            if k == "meta":
                assert _meta(a) == _meta(b)
            else:
                assert np.array_equal(a[k], b[k]), k          # bitwise (NaN nowhere in a design)
    with np.load(tmp_path / "a" / "mc.npz") as a, np.load(tmp_path / "b" / "mc.npz") as b:
        for k in a.files:
            assert np.array_equal(a[k], b[k]), k
