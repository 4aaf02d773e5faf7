"""The field basis' two methods side by side: 0.8.0's SVD and the Gram one (no assertions).

Every identification streams its field responses into an incremental orthonormal basis
(`sep_control.design.basis`). "svd" finds a block's new directions by an SVD of the b x n_f
residual block and a QR of them (0.8.0's arithmetic, experiment plan 0.8); "gram" (plan 0.9) from
the b x b Gram matrix, CholeskyQR2 and a b x K SVD. For each `bench_scale.py` row, one
identification around the scenario's initial input with the design's plan 0.9 TV-ERA settings
(its field basis tolerance, 1e-6 of the largest response, or `--field-tol`: 0.8.0's was 1e-8),
once per method, in one run and with one BLAS thread, measures:

* the identification's seconds, of it the plant's steps and the basis (`add` and `merge`);
* the basis rank r_f, and the field responses' relative difference from "svd"'s
  |Phi_g Yc_g - Phi_s Yc_s|_F / |Phi_s Yc_s|_F (against the tolerance);
* the output Markov parameters' largest difference (none: the basis holds the fields only).

    OPENBLAS_NUM_THREADS=1 python bench/bench_field_basis.py                    # plate:64, plate:128
    OPENBLAS_NUM_THREADS=1 python bench/bench_field_basis.py --rows plate:256   # ~4 min
    OPENBLAS_NUM_THREADS=1 python bench/bench_field_basis.py --field-tol 1e-8   # 0.8.0's tolerance
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_scale import ROWS  # noqa: E402  (the rows' scenarios and grids)

from sep_control.design import basis as basis_mod  # noqa: E402
from sep_control.design.pipeline import DesignSettings  # noqa: E402
from sep_control.evaluation.metrics import format_table  # noqa: E402
from sep_plant.scenario import load_scenario  # noqa: E402

COLUMNS = ["n_x", "tol", "identify_s", "plant_s", "basis_s", "basis/svd", "r_f", "field_vs_svd",
           "outputs_vs_svd"]


class Clock:
    """Seconds inside the plant's step and inside the basis' top-level `add` and `merge`."""

    def __init__(self):
        self.plant = self.basis = 0.0
        self._depth = 0

    def wrap(self, fn, attr: str):
        def timed(*a, **kw):
            outer = self._depth == 0
            self._depth += 1
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                self._depth -= 1
                if outer:
                    setattr(self, attr, getattr(self, attr) + time.perf_counter() - t0)
        return timed


def field_difference(a, b) -> float:
    """|Phi_a Yc_a - Phi_b Yc_b|_F / |Phi_b Yc_b|_F from the coefficients (Phi orthonormal): the
    part on Phi_a, Yc_a - T Yc_b (T = Phi_a' Phi_b), and the part outside it, M Yc_b with
    M = Phi_b - Phi_a T formed explicitly (no cancellation of two large norms)."""
    ya, yb = (d.Yc.transpose(2, 0, 1, 3).reshape(d.Yc.shape[2], -1) for d in (a, b))
    T = a.basis.T @ b.basis
    M = b.basis - a.basis @ T
    inside = float(np.sum((ya - T @ yb) ** 2))
    outside = float(np.sum(yb * ((M.T @ M) @ yb)))
    return float(np.sqrt((inside + max(outside, 0.0)) / np.sum(yb ** 2)))


def run_row(name: str, field_tol: float | None = None) -> list[dict]:
    file, changes = ROWS[name]
    scen = load_scenario(REPO / "sep_plant" / "scenarios" / file if file else None).with_plant(**changes)
    plant, problem = scen.plant, scen.problem
    rom = DesignSettings.for_scenario(scen, experiment_plan="0.9", field_tol=field_tol).rom(None, problem)
    U = problem.u_start(plant.n_u)
    rows, data = [], {}
    for method in ("svd", "gram"):
        clock = Clock()
        step = plant.step
        plant.step = clock.wrap(step, "plant")
        add, merge = basis_mod.IncrementalBasis.add, basis_mod.IncrementalBasis.merge
        basis_mod.IncrementalBasis.add = clock.wrap(add, "basis")
        basis_mod.IncrementalBasis.merge = clock.wrap(merge, "basis")
        try:
            t0 = time.perf_counter()
            ident = replace(rom, field_basis=method).identify(plant, U)
            total = time.perf_counter() - t0
        finally:
            basis_mod.IncrementalBasis.add, basis_mod.IncrementalBasis.merge = add, merge
            del plant.step
        data[method] = ident.data
        rows.append({"row": name, "n_x": int(plant.n_x), "method": method, "tol": rom.field_tol, "identify_s": total,
                     "plant_s": clock.plant, "basis_s": clock.basis, "r_f": int(ident.data.basis.shape[1])})
        print(f"  {name} {method}: {total:.1f} s", file=sys.stderr, flush=True)
    for r in rows:
        r["basis/svd"] = r["basis_s"] / rows[0]["basis_s"]
        r["field_vs_svd"] = field_difference(data[r["method"]], data["svd"])
        r["outputs_vs_svd"] = float(np.abs(data[r["method"]].Y - data["svd"].Y).max())
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", nargs="+", choices=list(ROWS), default=["plate:64", "plate:128"],
                    help="bench_scale.py rows (default: plate:64 plate:128)")
    ap.add_argument("--field-tol", type=float, default=None,
                    help="the field basis' relative tolerance (default: plan 0.9's, 1e-6)")
    args = ap.parse_args()
    out = {}
    with threadpool_limits(1):
        for name in args.rows:
            out.update({f"{r['row']} {r['method']}": r for r in run_row(name, args.field_tol)})
    print(format_table(out, COLUMNS))
    return 0


if __name__ == "__main__":
    sys.exit(main())
