"""How the design scales with the grid: one table across plants and grids (no assertions).

Rows: slab n_x = 100, 1600, 10^4 (the reference problem); plate 64^2, 128^2, 256^2 (the problem
of sep_plant/scenarios/plate.yaml); block 24^3, 32^3 (block.yaml). Each row runs in its own
process (so its peak resident memory is its own) and measures, in one run:

* n_x, one noise-free rollout of the horizon [s];
* the design with the scenario's settings (the defaults and its `design:` section): total,
  optimize, identify, gains [s]; the time spent inside the plant's own `step` during it, and
  design / plant-step time (the design's overhead over the floor its experiments set), the
  plant's step per node-step ("ns/node-step") and the design's own work outside it per node-step
  ("rest_ns": (design - plant steps) / (run-steps n_x), the figure `--against` compares across
  versions whose designs spend different run-steps); the ROM order and the field map's rank r_f;
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

`--device cuda` runs every row's experiments on the GPU (`sep_plant.device`: the experiment
batches stay on the device, docs/gpu.md); "plant steps" are then the device's step time (the
device is synchronized after each step to measure it) and each row also prints its per-stage
table: wall time, the device's step time, the host's time (the rest), megabytes moved each way,
run-steps, the device memory pool, one line per stage as the design logs it ending, then the
Monte Carlo. The 10^6-state rows plate:1000 and block:100 run only when named in `--rows` (on
one CPU core they would take days). `--log` prints the design's log lines as they come (with the
time), to stderr.
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
           "design/plant_steps", "run_steps_k", "nominal_k", "belief_k", "ident_k", "ns/node-step", "rest_ns", "n_r", "r_f", "peak_rss_mb", "file_mb",
           "mc_s_per_100", "in_band", "design/rollout", "mc100/rollout"]
STAGE_COLUMNS = ["wall_s", "device_step_s", "host_s", "MB_to_device", "MB_to_host", "run_steps_k", "pool_GB"]
AGAINST = ("design_s", "plant_step_s", "rest_ns", "run_steps_k", "peak_rss_mb", "mc_s_per_100")


def block_label(value: str) -> str:
    return "one piece" if value == "0" else ("blocks" if value == "default" else f"blocks of {value}")


class Sampler:
    """A sampling profile of this process's main thread (`--log`): every `interval` seconds the
    stack is read (`sys._current_frames`) and each function on it counted once, so a count is the
    share of the time spent inside that function, callees included (cProfile's cumulative time,
    without its overhead). Printed every `every` seconds (the stage in progress, to stderr) and on
    SIGTERM (a step of bench/device_run.sh that hits its timeout still says where the time went)."""

    def __init__(self, interval: float = 0.25, every: float = 30.0, stats=None):
        import collections
        import signal
        import threading

        self.interval, self.every, self.stats = interval, every, stats
        self.counts, self.samples = collections.Counter(), 0
        self.main = threading.main_thread().ident
        self.t0 = time.perf_counter()
        threading.Thread(target=self._run, daemon=True).start()
        signal.signal(signal.SIGTERM, self._term)

    def _run(self) -> None:
        last = time.perf_counter()
        while True:
            time.sleep(self.interval)
            frame = sys._current_frames().get(self.main)
            seen = set()
            while frame is not None:
                code = frame.f_code
                key = f"{Path(code.co_filename).name}:{code.co_name}"
                if key not in seen and ("sep_" in code.co_filename or "bench" in code.co_filename
                                        or "cupy" in code.co_filename or "numpy" in code.co_filename):
                    seen.add(key)
                    self.counts[key] += 1
                frame = frame.f_back
            self.samples += 1
            if time.perf_counter() - last >= self.every:
                last = time.perf_counter()
                self.report("progress")

    def report(self, why: str, top: int = 22) -> None:
        el = time.perf_counter() - self.t0
        extra = "" if self.stats is None else f"; device stats {self.stats.snapshot()}"
        lines = [f"[{time.strftime('%H:%M:%S')}] sampled profile ({why}, {el:.0f} s, {self.samples} samples){extra}"]
        shown = [(k, n) for k, n in self.counts.most_common() if n < 0.97 * self.samples][:top]   # not the outer frames
        for key, n in shown:
            lines.append(f"    {100.0 * n / max(1, self.samples):5.1f} %  {key}")
        print("\n".join(lines), file=sys.stderr, flush=True)

    def _term(self, signum, frame) -> None:
        self.report("stopped by SIGTERM")
        sys.exit(124)


class StageClock:
    """The per-stage table of a device row: a snapshot of the device plant's `stats` whenever the
    design logs a stage's end (and at the explicit marks), differences between snapshots."""

    def __init__(self, plant, echo: bool = False):
        self.plant, self.echo, self.rows = plant, echo, {}
        self.t = time.perf_counter()
        self.last = plant.stats.snapshot()

    def mark(self, label: str) -> None:
        now, snap = time.perf_counter(), self.plant.stats.snapshot()
        d = {k: snap[k] - self.last[k] for k in snap}
        wall = now - self.t
        pool = getattr(self.plant.xp, "get_default_memory_pool", None)
        key, n = label, 2
        while key in self.rows:
            key, n = f"{label} ({n})", n + 1
        self.rows[key] = {"wall_s": wall, "device_step_s": d["step_s"], "host_s": wall - d["step_s"],
                          "MB_to_device": d["to_device"] / 1e6, "MB_to_host": d["to_host"] / 1e6,
                          "run_steps_k": d["run_steps"] / 1e3,
                          "pool_GB": pool().total_bytes() / 1e9 if pool else float("nan")}
        if self.echo:
            print(f"[{time.strftime('%H:%M:%S')}] {key}: {self.rows[key]}", file=sys.stderr, flush=True)
        self.t, self.last = now, snap

    def log(self, message: str) -> None:
        """The design's log callback: a stage ended."""
        if self.echo:
            print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)
        words = message.split(":")[0].split("(")[0].strip()
        self.mark(words[:40])


def run_row(name: str, runs: int, dask: str | None = None, block_nodes: str = "default",
            device: str = "cpu", echo: bool = False, threads: int = 1, plan: str | None = None,
            memory_budget: str | None = None) -> dict:
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
    if device == "emulated":               # the tests' CPU stand-in for a GPU: checks this script without one
        sys.path.insert(0, str(REPO / "tests"))
        from device_guard import guard
        plant = on_device(plant, "cuda", xp=guard)
    else:
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

    on_gpu = device != "cpu"
    with threadpool_limits(threads), open_engine(dask) as engine:
        U0 = problem.u_start(plant.n_u)
        t0 = time.perf_counter()
        nominal_states(plant, U0)          # on a GPU: CuPy compiles the step's kernels here
        warmup = time.perf_counter() - t0
        t0 = time.perf_counter()
        nominal_states(plant, U0)
        rollout = time.perf_counter() - t0
        plant.step = timed_step
        clock = None
        if on_gpu:
            plant.timing = True            # synchronize after each step: the device's step time
            clock = StageClock(plant, echo)
        sampler = Sampler(stats=plant.stats if on_gpu else None) if echo else None
        t0 = time.perf_counter()
        # a tree older than the key (0.8.0 with --against) runs its own plan, which plan 0.8 reproduces
        known = plan and "experiment_plan" in DesignSettings.__dataclass_fields__
        settings = DesignSettings.for_scenario(scen, **({"experiment_plan": plan} if known else {}))
        if memory_budget:                  # the design's memory budget (sep >= 0.4): otherwise this machine's free memory
            from dataclasses import replace

            from sep_control.compute.budget import parse_budget
            settings = replace(settings, memory_budget=parse_budget(memory_budget))
        design = run_design(plant, problem, settings, show_progress=False,
                            log=clock.log if clock else (lambda m: None), engine=engine)
        t_design = time.perf_counter() - t0
        if clock:
            clock.mark("design end (gains, field map)")
        plant_s, run_steps = spent
        if on_gpu:
            plant_s, run_steps = plant.stats.step_s, plant.stats.run_steps
        del plant.step
        with tempfile.TemporaryDirectory() as tmp:
            path = save_design(Path(tmp) / "d.npz", design)
            file_mb = path.stat().st_size / 1e6
        t0 = time.perf_counter()
        mc = simulate(plant, design, "rom_lqg", 1, runs, keep_estimates=0, keep_trajectories=0, engine=engine)
        t_mc = (time.perf_counter() - t0) * 100.0 / runs
        if clock:
            clock.mark(f"Monte Carlo ({runs} runs)")
        if sampler:
            sampler.report("row end")
    tm = design.meta["timings"]
    G = design.rom.G
    stages = design.meta.get("run_steps", {})      # per stage (sep >= 0.9; absent: a checkout before)
    per_stage = {f"{k[:5] if k == 'identification' else k}_k": stages[k] / 1e3 if k in stages else None
                 for k in ("nominal", "belief", "identification")}
    return {**per_stage,"n_x": plant.n_x, "rollout_s": rollout, "design_s": t_design, "optimize_s": tm["optimize_s"],
            "identify_s": tm["identify_s"], "gains_s": tm["gains_s"], "plant_step_s": plant_s,
            "design/plant_steps": t_design / plant_s, "run_steps_k": run_steps / 1e3,
            "ns/node-step": 1e9 * plant_s / (run_steps * plant.n_x),
            "rest_ns": 1e9 * (t_design - plant_s) / (run_steps * plant.n_x), "n_r": int(design.rom.dims.max()),
            "r_f": int(getattr(G, "rank", G.n)), "file_mb": file_mb, "mc_s_per_100": t_mc,
            "in_band": mc.summary["in_band"], "mc_cost": mc.summary["cost_mean"],
            "J_nominal": design.meta["optimizer"]["nominal_cost"],
            "design/rollout": t_design / rollout, "mc100/rollout": t_mc / rollout,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, "device": device,
            "warmup_s": warmup, "mc_in_band": mc.summary["in_band"], "stages": clock.rows if clock else {}}


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
    ap.add_argument("--device", choices=["cpu", "cuda", "emulated"], default="cpu",
                    help="where the plants step (cuda: CuPy on a GPU, see sep_plant.device; emulated: the "
                         "tests' CPU emulator of a GPU, tests/device_guard.py, to try this script without one)")
    ap.add_argument("--against", metavar="DIR",
                    help="also run every row with the sep packages of the checkout DIR (alternating) and "
                         "print this tree's ratios to it")
    ap.add_argument("--log", action="store_true", help="print the design's log lines (and, on a GPU, each "
                    "stage's row) to stderr as they come")
    ap.add_argument("--threads", type=int, default=1, help="BLAS threads of the design's host work (default 1)")
    ap.add_argument("--experiment-plan", choices=["0.8", "0.9"], default=None,
                    help="the design's experiment plan (default: the scenario's, i.e. 0.9; see `sep design --help`)")
    ap.add_argument("--memory-budget", metavar="SIZE",
                    help="the designs' memory budget (e.g. 1G; default: each design's own, from the free "
                         "memory, which sets sep 0.8.0's field blocks and so its time per node-step)")
    ap.add_argument("--row", help=argparse.SUPPRESS)        # internal: run one row, print JSON
    args = ap.parse_args()
    for v in args.block_nodes:
        if v != "default" and not v.isdigit():
            ap.error(f"--block-nodes: expected a number of nodes or 'default', got {v!r}")
    if args.memory_budget:
        from sep_control.compute.budget import parse_budget
        try:
            parse_budget(args.memory_budget)
        except ValueError as exc:
            ap.error(f"--memory-budget: {exc}")
    if args.row:
        print(json.dumps(run_row(args.row, args.runs, args.dask, args.block_nodes[0], args.device, args.log,
                                 args.threads, args.experiment_plan, args.memory_budget)))
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
                                       "--block-nodes", value, "--device", args.device,
                                       "--threads", str(args.threads)]
                                      + (["--experiment-plan", args.experiment_plan] if args.experiment_plan else [])
                                      + (["--memory-budget", args.memory_budget] if args.memory_budget else [])
                                      + (["--dask", args.dask] if args.dask else []) + (["--log"] if args.log else []),
                                      env=env, stdout=subprocess.PIPE, stderr=None if args.log else subprocess.PIPE,
                                      text=True)
                if proc.returncode != 0:
                    print(f"{label}: failed ({proc.returncode}): {(proc.stderr or '').strip().splitlines()[-1:]}",
                          flush=True)
                    continue
                rows[label] = json.loads(proc.stdout.strip().splitlines()[-1])
                print(f"{label}: {time.perf_counter() - t0:.0f} s", flush=True)
    from sep_control.evaluation.metrics import format_table

    print(f"\nOne run per row, {args.threads} BLAS thread(s), this machine, plants on {args.device}; ratios measured in the same run")
    print(format_table(rows, COLUMNS))
    for label, row in rows.items():
        if row.get("stages"):
            print(f"\n{label} on {args.device}, per stage (device: the plant's steps, synchronized; host: the "
                  f"rest; first rollout, kernel compilation included: {row['warmup_s']:.2f} s)")
            print(format_table(row["stages"], STAGE_COLUMNS))
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
