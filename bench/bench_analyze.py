"""Bag analysis speed and the recorder's effect on the real-time loop (issue 4; no assertions).

1. analysis: synthetic bags of the reference scenario (the slab, n_x = 100, N = 250: a 62.5 s
   episode, contract layout, written with rosbags) -> `analyze` per bag (target < 2 s), `analyze`
   + report with figures, and `aggregate` + report over `--bags` bags (target: 50 bags < 30 s);
   then one synthetic 2-D grid-plant bag (`--grid`, with its image topics) analysed with its
   heat-map report.
2. recorder: plant (real-time mode) + lqg processes for one episode, with and without the
   `record` process; prints the plant's deadline misses and measurement->command latency.
   Uses `--design` if given, else designs a small scenario on the fly (`--rt-scenario`).

    python bench/bench_analyze.py                      # both parts
    python bench/bench_analyze.py --skip-recorder --bags 50
    python bench/bench_analyze.py --skip-recorder --bags 2          # smoke run
    python bench/bench_analyze.py --skip-analysis --real-time-factor 10 --repeats 2
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
for p in ("tests", "sep_plant", "sep_estimator", "sep_control"):
    sys.path.insert(0, str(REPO / p))
SRC = os.pathsep.join(str(REPO / p) for p in ("sep_plant", "sep_estimator", "sep_control"))


def bench_analysis(n_bags: int, work: Path, grid: tuple[int, ...]) -> None:
    from bag_synth import fake_design, grid_episode, synthetic_episode, write_bag
    from sep_control.bags.analysis import aggregate, analyze
    from sep_control.bags.report import write_report
    from sep_estimator.design_file import save_design
    from sep_plant.scenario import reference

    s = reference()
    t0 = time.perf_counter()
    eps = [synthetic_episode(s, seed=i) for i in range(min(n_bags, 5))]
    bags = [write_bag(work / f"ep{i:03d}", eps[i % len(eps)]) for i in range(n_bags)]
    design = save_design(work / "design.npz", fake_design(eps[0], n_r=20))
    size = sum(f.stat().st_size for f in bags[0].iterdir())
    print(f"wrote {n_bags} synthetic reference bags ({size / 1e6:.2f} MB each) in {time.perf_counter() - t0:.1f} s")

    times = []
    for b in bags[:5]:
        t = time.perf_counter()
        rep = analyze(b, design)
        times.append(time.perf_counter() - t)
    print(f"analyze one 62.5 s bag: median {sorted(times)[len(times) // 2]:.3f} s, max {max(times):.3f} s "
          f"(target < 2 s)  [{rep.episode.n_steps} steps, {sum(rep.episode.counts.values())} messages]")
    t = time.perf_counter()
    rep = analyze(bags[0], design)
    write_report(rep, work / "one_report")
    print(f"analyze + report with 3 figures, one bag: {time.perf_counter() - t:.3f} s")
    t = time.perf_counter()
    agg = aggregate(bags, design)
    t_agg = time.perf_counter() - t
    write_report(agg, work / "agg_report")
    print(f"aggregate {n_bags} bags: {t_agg:.2f} s analysis, {time.perf_counter() - t:.2f} s with report "
          f"(target < 30 s for 50)")

    g = grid_episode(grid, n_steps=250)
    bag = write_bag(work / "grid", g)
    t = time.perf_counter()
    rep = analyze(bag, fake_design(g))
    t_grid = time.perf_counter() - t
    write_report(rep, work / "grid_report")
    print(f"grid plant {' x '.join(map(str, grid))} ({g.info.n_field} nodes, {rep.episode.n_steps} steps, images): "
          f"analyze {t_grid:.3f} s, {time.perf_counter() - t:.3f} s with the heat-map report")


def _run_episode(work: Path, design: Path, scen: Path | None, rtf: float, record: bool, tag: str) -> dict:
    env = dict(os.environ, PYTHONPATH=SRC, PYTHONUNBUFFERED="1")
    procs = []

    def start(args, name):
        log = open(work / f"{tag}_{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", *args], cwd=work, env=env, stdout=log, stderr=subprocess.STDOUT,
                             stdin=subprocess.DEVNULL)
        procs.append(p)
        return p

    try:
        ready = work / f"{tag}_ready"
        if record:
            start(["sep_control.ros.record_node", "--out", str(work / f"{tag}_bag"), "--final-grace", "0.5",
                   "--ready-file", str(ready), "--ready-topics", "command", "state_estimate",
                   "field_estimate"], "record")
        start(["sep_control.ros.lqg_node", "--ros-args", "-p", f"design_file:={design}"], "lqg")
        t0 = time.monotonic()
        while record and not ready.exists() and time.monotonic() - t0 < 60:
            time.sleep(0.05)
        args = ["sep_plant.ros.plant_node", "--ros-args", "-p", "mode:=realtime", "-p", f"real_time_factor:={rtf}",
                "-p", f"summary_file:={tag}_plant.json", "-p", f"wait_for_subscribers:={2 if record else 1}",
                "-p", f"wait_for_field_subscribers:={1 if record else 0}"]
        if scen:
            args += ["-p", f"scenario_file:={scen}"]
        plant = start(args, "plant")
        plant.wait(600)
        for p in procs:
            p.wait(60)
        return json.loads((work / f"{tag}_plant.json").read_text())
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(10)


def rt_scenario_of(spec: str):
    """The slab scenario of 'key=value,...' (problem keys to the problem, the rest to the plant)."""
    from sep_plant.problem import Problem
    from sep_plant.scenario import Scenario

    kw = {k: int(v) for k, v in (kv.split("=") for kv in spec.split(","))}
    problem = {k: v for k, v in kw.items() if k in Problem.__dataclass_fields__}
    plant = {k: v for k, v in kw.items() if k not in problem}
    return Scenario("slab", plant, Problem(**problem)).canonical()


def bench_recorder(work: Path, design: str | None, rtf: float, repeats: int, rt_scenario: str) -> None:
    os.environ.setdefault("ROS_DOMAIN_ID", str(150 + os.getpid() % 50))
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    scen = None
    if design is None:
        import yaml

        from sep_control.design.pipeline import run_design
        from sep_estimator.design_file import save_design

        s = rt_scenario_of(rt_scenario)
        t = time.perf_counter()
        d = run_design(s.plant, s.problem, show_progress=False, log=lambda *a, **k: None)
        design = str(save_design(work / "rt_design.npz", d))
        scen = work / "rt.yaml"
        data = s.to_dict()
        data.pop("format"), data.pop("version")
        scen.write_text(yaml.safe_dump(data))
        print(f"designed scenario {rt_scenario} in {time.perf_counter() - t:.1f} s")
    print(f"real-time episodes at real_time_factor {rtf}: plant + lqg, with / without the recorder")
    print(f"{'run':<18} {'steps':>5} {'deadline_misses':>15} {'lat p50 ms':>10} {'lat p99 ms':>10} {'wall s':>7}")
    for r in range(repeats):
        for record in (False, True):
            tag = f"{'rec' if record else 'norec'}{r}"
            sm = _run_episode(work, Path(design), scen, rtf, record, tag)
            print(f"{('with recorder' if record else 'without recorder') + f' #{r}':<18} {sm['steps']:>5} "
                  f"{sm['deadline_misses']:>15} {1e3 * sm['latency_p50_s']:>10.3f} {1e3 * sm['latency_p99_s']:>10.3f} "
                  f"{sm['wall_s']:>7.2f}")
            if record:
                from sep_control.bags.analysis import analyze

                m = analyze(work / f"{tag}_bag", design).metrics
                print(f"{'':<18} bag: complete={m['complete']} deadline_misses={m['deadline_misses']} "
                      f"latency p50 {1e3 * m['latency_p50_s']:.3f} ms p99 {1e3 * m['latency_p99_s']:.3f} ms "
                      "(recorder clock)")


def main() -> None:
    from sep_control.cli.common import add_deprecated, set_prog

    set_prog("bench_analyze")                   # the deprecation line names this script
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bags", type=int, default=50)
    ap.add_argument("--skip-analysis", action="store_true")
    ap.add_argument("--skip-recorder", action="store_true")
    ap.add_argument("--design", help="design file for the real-time part (reference scenario)")
    ap.add_argument("--real-time-factor", type=float, default=10.0,
                    help="plant real_time_factor (default 10: 25 ms steps)")
    add_deprecated(ap, "--rtf", "--real-time-factor", "real_time_factor", type=float)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--grid", default="40x30", help="grid of the synthetic 2-D plant bag (default 40x30)")
    ap.add_argument("--rt-scenario", default="n_x=100,n_steps=250",
                    help="scenario designed on the fly when --design is not given (default: the reference grid)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_analyze_") as tmp:
        work = Path(tmp)
        if not args.skip_analysis:
            bench_analysis(args.bags, work, tuple(int(n) for n in args.grid.split("x")))
        if not args.skip_recorder:
            bench_recorder(work, args.design, args.real_time_factor, args.repeats, args.rt_scenario)


if __name__ == "__main__":
    main()
