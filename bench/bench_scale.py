"""How the design scales with the grid: one table across plants and grids (no assertions).

Rows: slab n_x = 100, 1600, 10^4 (the reference problem); plate 64^2, 128^2, 256^2 (the problem
of sep_plant/scenarios/plate.yaml); block 24^3, 32^3 (block.yaml). Each row runs in its own
process (so its peak resident memory is its own) and measures, in one run:

* n_x, one noise-free rollout of the horizon [s];
* the design with the scenario's settings (the defaults and its `design:` section): total,
  optimize, identify, gains [s]; the time spent inside the plant's own `step` during it, and
  design / plant-step time (the design's overhead over the floor its experiments set); the ROM
  order and the field map's rank r_f;
* the peak resident memory of the row's process, the design file's size;
* a Monte Carlo of ROM-LQG: seconds per 100 runs, in-band share (`--runs`, default 100);
* ratios to one rollout.

    OPENBLAS_NUM_THREADS=1 python bench/bench_scale.py --quick     # the small rows (~2 min)
    OPENBLAS_NUM_THREADS=1 python bench/bench_scale.py             # every row (long: hours)
    python bench/bench_scale.py --rows slab:1600 plate:128          # chosen rows
    python bench/bench_scale.py --rows block:24 --block-nodes 0 default   # batch in one piece vs blocks
    python bench/bench_scale.py --device cuda --rows plate:1000 block:100  # 10^6 states on a GPU (CuPy)
    python bench/bench_scale.py --quick --against /tmp/sep-0.6      # this tree vs another checkout

`--block-nodes` runs every row once per value: the built-in plants' `block_nodes` (the batch is
stepped in blocks of that many nodes, `sep_plant.plants.blocks`; 0: in one piece; default: the
plants' own), and ends with the design, plant-step and Monte Carlo times of each value relative
to the first.

`--against DIR` runs every row twice, alternating, in the same run: with the sep packages of
another checkout DIR (sep >= 0.6, e.g. `git worktree add /tmp/sep-0.6 <commit>`) and with this
tree's, the harness being this script both times; it ends with the ratios of this tree to DIR
(design time, plant steps, run-steps, peak memory) and the nominal cost's relative difference.

`--device cuda` steps every row's plant on the GPU (`sep_plant.device`: the state crosses the bus
each step; "plant steps" then include the transfers). The 10^6-state rows plate:1000 and
block:100 run only when named in `--rows` (on one CPU core they would take days).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ROWS = {                       # name -> (scenario file or None for the reference, plant key changes)
    "slab:100": (None, {"n_x": 100}),
    "slab:1600": (None, {"n_x": 1600}),
    "slab:10000": (None, {"n_x": 10_000}),
    "plate:64": ("plate.yaml", {"nodes": [64, 64]}),
    "plate:128": ("plate.yaml", {"nodes": [128, 128]}),
    "plate:256": ("plate.yaml", {"nodes": [256, 256]}),
    "block:24": ("block.yaml", {"nodes": [24, 24, 24]}),
    "block:32": ("block.yaml", {"nodes": [32, 32, 32]}),
    "plate:1000": ("plate.yaml", {"nodes": [1000, 1000]}),        # 10^6 states: --rows only (GPU)
    "block:100": ("block.yaml", {"nodes": [100, 100, 100]}),
}
DEFAULT_ROWS = [r for r in ROWS if r not in ("plate:1000", "block:100")]
QUICK = ("slab:100", "slab:1600", "plate:64")
COLUMNS = ["n_x", "rollout_s", "design_s", "optimize_s", "identify_s", "gains_s", "plant_step_s",
           "design/plant_steps", "run_steps_k", "nominal_k", "belief_k", "ident_k", "ns/node-step", "n_r", "r_f", "peak_rss_mb", "file_mb",
           "mc_s_per_100", "in_band", "design/rollout", "mc100/rollout"]
AGAINST = ("design_s", "plant_step_s", "run_steps_k", "peak_rss_mb", "mc_s_per_100")


def block_label(value: str) -> str:
    return "one piece" if value == "0" else ("blocks" if value == "default" else f"blocks of {value}")


def run_row(name: str, runs: int, dask: str | None = None, block_nodes: str = "default",
            device: str = "cpu") -> dict:
    """Measure one row (in this process)."""
    import numpy as np
    from threadpoolctl import threadpool_limits

    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_control.evaluation.montecarlo import simulate
    from sep_estimator.design_file import save_design
    from sep_plant.device import on_device
    from sep_plant.protocol import nominal_states
    from sep_plant.scenario import load_scenario

    file, changes = ROWS[name]
    scen = load_scenario(REPO / "sep_plant" / "scenarios" / file if file else None).with_plant(**changes)
    plant, problem = scen.plant, scen.problem
    plant = on_device(plant, device)
    if block_nodes != "default":           # on cuda: the blocks sent to the device
        plant.block_nodes = int(block_nodes) or 1 << 62
    spent = [0.0, 0]
    step = plant.step

    def timed_step(X, *a, **kw):           # the plant's own work, measured from outside
        t0 = time.perf_counter()
        out = step(X, *a, **kw)
        spent[0] += time.perf_counter() - t0
        spent[1] += X.shape[0]              # run-steps
        return out

    from sep_control.compute.engine import open_engine

    with threadpool_limits(1), open_engine(dask) as engine:
        U0 = problem.u_start(plant.n_u)
        nominal_states(plant, U0)
        t0 = time.perf_counter()
        nominal_states(plant, U0)
        rollout = time.perf_counter() - t0
        plant.step = timed_step
        t0 = time.perf_counter()
        design = run_design(plant, problem, DesignSettings.for_scenario(scen), show_progress=False,
                            log=lambda m: None, engine=engine)
        t_design = time.perf_counter() - t0
        plant_s, run_steps = spent
        del plant.step
        with tempfile.TemporaryDirectory() as tmp:
            path = save_design(Path(tmp) / "d.npz", design)
            file_mb = path.stat().st_size / 1e6
        t0 = time.perf_counter()
        mc = simulate(plant, design, "rom_lqg", 1, runs, keep_estimates=0, keep_trajectories=0, engine=engine)
        t_mc = (time.perf_counter() - t0) * 100.0 / runs
    tm = design.meta["timings"]
    G = design.rom.G
    stages = design.meta.get("run_steps", {})      # per stage (sep >= 0.9; absent: a checkout before)
    per_stage = {f"{k[:5] if k == 'identification' else k}_k": stages[k] / 1e3 if k in stages else None
                 for k in ("nominal", "belief", "identification")}
    return {**per_stage,"n_x": plant.n_x, "rollout_s": rollout, "design_s": t_design, "optimize_s": tm["optimize_s"],
            "identify_s": tm["identify_s"], "gains_s": tm["gains_s"], "plant_step_s": plant_s,
            "design/plant_steps": t_design / plant_s, "run_steps_k": run_steps / 1e3,
            "ns/node-step": 1e9 * plant_s / (run_steps * plant.n_x), "n_r": int(design.rom.dims.max()),
            "r_f": int(getattr(G, "rank", G.n)), "file_mb": file_mb, "mc_s_per_100": t_mc,
            "in_band": mc.summary["in_band"], "mc_cost": mc.summary["cost_mean"],
            "J_nominal": design.meta["optimizer"]["nominal_cost"],
            "design/rollout": t_design / rollout, "mc100/rollout": t_mc / rollout,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "device": device}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help=f"only the small rows {', '.join(QUICK)}")
    ap.add_argument("--rows", nargs="+", choices=list(ROWS), help="rows to run (default: all)")
    ap.add_argument("--runs", type=int, default=100, help="Monte Carlo runs of ROM-LQG per row")
    ap.add_argument("--json", metavar="PATH", help="also write the rows as JSON")
    ap.add_argument("--dask", metavar="WHERE", help="run every row's experiments and Monte Carlo on Dask "
                    "(local, local:N, tcp://HOST:PORT); 'plant steps in the design' then counts the client's only")
    ap.add_argument("--block-nodes", nargs="+", default=["default"], metavar="N",
                    help="run each row once per value: nodes per block of the plants' batched step "
                         "(0: the batch in one piece; default: the plants' own)")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="where the plants step (cuda: CuPy on a GPU, see sep_plant.device)")
    ap.add_argument("--against", metavar="DIR",
                    help="also run every row with the sep packages of the checkout DIR (alternating) and "
                         "print this tree's ratios to it")
    ap.add_argument("--row", help=argparse.SUPPRESS)        # internal: run one row, print JSON
    args = ap.parse_args()
    for v in args.block_nodes:
        if v != "default" and not v.isdigit():
            ap.error(f"--block-nodes: expected a number of nodes or 'default', got {v!r}")
    if args.row:
        print(json.dumps(run_row(args.row, args.runs, args.dask, args.block_nodes[0], args.device)))
        return 0
    names = args.rows or (list(QUICK) if args.quick else DEFAULT_ROWS)
    trees = ([(f"@{Path(args.against).name}", Path(args.against).resolve())] if args.against else []) + [("", REPO)]
    if args.against and not (trees[0][1] / "sep_control" / "sep_control").is_dir():
        ap.error(f"--against: {args.against} is not a sep checkout (no sep_control/sep_control)")
    rows = {}
    compare = len(args.block_nodes) > 1
    for name in names:
        for value in args.block_nodes:
            for tag, root in trees:              # alternating: load drifts hit both alike
                label = (f"{name} {block_label(value)}" if compare else name) + (f" {tag}" if tag else "")
                env = dict(os.environ, PYTHONPATH=os.pathsep.join(
                    str(root / p) for p in ("sep_plant", "sep_estimator", "sep_control")))
                t0 = time.perf_counter()
                proc = subprocess.run([sys.executable, __file__, "--row", name, "--runs", str(args.runs),
                                       "--block-nodes", value, "--device", args.device]
                                      + (["--dask", args.dask] if args.dask else []),
                                      env=env, capture_output=True, text=True)
                if proc.returncode != 0:
                    print(f"{label}: failed ({proc.returncode}): {proc.stderr.strip().splitlines()[-1:]}", flush=True)
                    continue
                rows[label] = json.loads(proc.stdout.strip().splitlines()[-1])
                print(f"{label}: {time.perf_counter() - t0:.0f} s", flush=True)
    from sep_control.evaluation.metrics import format_table

    print(f"\nOne run per row, one BLAS thread, this machine, plants on {args.device}; ratios measured in the same run")
    print(format_table(rows, COLUMNS))
    if compare:
        first = block_label(args.block_nodes[0])
        ratios = {}
        for name in names:
            base = rows.get(f"{name} {first}")
            for value in args.block_nodes[1:]:
                row = rows.get(f"{name} {block_label(value)}")
                if base and row:
                    ratios[f"{name} {block_label(value)}"] = {
                        f"{k} / {first}": row[k] / base[k] for k in ("design_s", "plant_step_s", "mc_s_per_100")}
        print(f"\nRelative to {first} (same run)")
        print(format_table(ratios, [f"{k} / {first}" for k in ("design_s", "plant_step_s", "mc_s_per_100")]))
    if args.against:
        tag = trees[0][0]
        ratios = {}
        for label, row in rows.items():
            base = rows.get(f"{label} {tag}")
            if base is None:
                continue
            ratios[label] = {f"{k} / {tag}": row[k] / base[k] for k in AGAINST}
            ratios[label]["J_nominal rel. diff"] = abs(row["J_nominal"] - base["J_nominal"]) / base["J_nominal"]
            ratios[label]["mc_cost rel. diff"] = abs(row["mc_cost"] - base["mc_cost"]) / base["mc_cost"]
        print(f"\nThis tree relative to {args.against} (same run, alternating)")
        print(format_table(ratios, [f"{k} / {tag}" for k in AGAINST] + ["J_nominal rel. diff", "mc_cost rel. diff"]))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
