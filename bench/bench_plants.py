"""Cost and accuracy of the built-in plants' time steps: one table (no assertions; one run).

Per plant (slab n_x = 100 and 10^4, plate 64^2 and 128^2, block 24^3, Allen-Cahn 50^2):
* cost: ns per node-step of ONE batched step at batch sizes 1 and 64 (and 200 for the slab),
  best of several repeats (the machine may be shared), and ms per step of one run;
* accuracy: the scheme at its default dt after a fixed horizon (default 10 s) from the default
  initial state under a constant input (0.1 per heater/lamp, 0.05 per Allen-Cahn actuator),
  against fine-step references, relative to the largest change of the field over the horizon:
  (a) the same scheme at dt/64 and dt/128, Richardson-extrapolated (first order:
  2 x_{dt/128} - x_{dt/64}); (b) for the default-size grid plants also classical RK4 of the
  semi-discrete system (plant.rhs) at half its stability limit, an integrator independent of
  the split (its distance to (a) is printed: both references agree).

--solvers adds a second table: the grid plants' cost with each line solver of adi.py ("auto",
the default; "lapack": dptsv on every axis; "thomas": vectorized Thomas on every axis; "pcr":
parallel cyclic reduction, the GPU's solver, here on the CPU).

--blocks adds a table of the cost of the large batches the design steps (the sensitivity
experiments' N n_u runs, a TV-ERA chunk's runs) stepped in one piece and in blocks of 2^15 to
2^20 nodes (`sep_plant.plants.blocks`; the default block is marked), side by side in one run.

FMU plants (sep_plant.plants.fmu): the example rod (examples/fmu_rod, 50 nodes, 3 heaters, RK4
with 4 substeps per dt) is built from C source (needs a C compiler; skipped without one) and
stepped as a Model Exchange FMU by sep and as a Co-Simulation FMU by itself, FMI 2.0 and 3.0,
next to the same rod as a native numpy plant (tests/fmu_rod.py). "FMU calls alone" is the floor:
the same C calls in a tight loop with the same prebuilt arguments (ME: set states, set inputs,
get derivatives per run and RK4 stage; CS: deserialize, set state, set inputs, do step, get
outputs, get state, size, serialize per run); "doStep alone" is the FMU's own integration in C.
--only-fmu prints this table alone, and then the design table: the whole design (`run_design`,
default settings) of examples/fmu_rod/scenario.yaml with the rod as Model Exchange FMU, as
Co-Simulation FMU (opaque states: the mean-only nominal, no EnKF) and as the native numpy rod,
with each design's nominal cost against the native one's; and the Model Exchange design again on
`--dask local:2`: its arrays against the in-process design and how often the FMU's bytes were
scattered to the workers (once: every map refers to the workers' copy).

--device cuda adds a table of batched steps on a GPU (CuPy, `sep_plant.device`) against one CPU
core, side by side in one run, up to 10^6 states: the device step with the state's round trip
over the bus (what `--device cuda` does), the step of a state resident on the device, and the
largest difference from the CPU step (relative to the field's change in the step).

    OPENBLAS_NUM_THREADS=1 python bench/bench_plants.py [--solvers] [--blocks] [--horizon 10] [--repeats 5]
    python bench/bench_plants.py --only-device --device cuda                 # on a machine with a GPU
    python bench/bench_plants.py --only-fmu                                  # the FMU plants alone
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from ctypes import byref, c_size_t
from pathlib import Path

import numpy as np

from sep_plant.device import DevicePlant, array_module
from sep_plant.plants import adi, blocks, make_plant

CASES = [  # label, type, config, batch sizes, constant input, RK4 reference
    ("slab 100", "slab", {"n_x": 100}, (1, 64, 200), 0.1, False),
    ("slab 10^4", "slab", {"n_x": 10_000}, (1, 64, 200), 0.1, False),
    ("plate 64^2", "plate", {}, (1, 64), 0.1, True),
    ("plate 128^2", "plate", {"nodes": [128, 128]}, (1, 64), 0.1, False),
    ("block 24^3", "block", {}, (1, 64), 0.1, True),
    ("allen_cahn 50^2", "allen_cahn", {}, (1, 64), 0.05, True),
]

BLOCK_CASES = [  # label, type, config, batch (the design's: N n_u sensitivity runs or a TV-ERA chunk)
    ("slab 10^4", "slab", {"n_x": 10_000}, 400),
    ("plate 64^2", "plate", {}, 720),
    ("plate 128^2", "plate", {"nodes": [128, 128]}, 720),
    ("plate 256^2", "plate", {"nodes": [256, 256]}, 360),
    ("block 24^3", "block", {}, 540),
    ("block 32^3", "block", {"nodes": [32, 32, 32]}, 540),
    ("allen_cahn 50^2", "allen_cahn", {}, 720),
]
BLOCK_SIZES = (15, 16, 17, 18, 19, 20)          # log2 of the nodes per block

DEVICE_CASES = [  # label, type, config, batch
    ("slab 10^4", "slab", {"n_x": 10_000}, 400),
    ("plate 256^2", "plate", {"nodes": [256, 256]}, 360),
    ("plate 1000^2", "plate", {"nodes": [1000, 1000]}, 16),
    ("block 32^3", "block", {"nodes": [32, 32, 32]}, 540),
    ("block 100^3", "block", {"nodes": [100, 100, 100]}, 16),
]


ROOT = Path(__file__).resolve().parent.parent
FMU_BATCHES = (1, 64, 400)


def best_seconds(fn, repeats: int, budget_s: float = 0.3) -> float:
    """Best-of-`repeats` seconds of one call of fn() (after a warm-up call; each repeat calls it
    as often as fits `budget_s` / `repeats`)."""
    fn()
    t0 = time.perf_counter()
    fn()
    reps = max(1, int(budget_s / max(time.perf_counter() - t0, 1e-6) / repeats))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(reps):
            fn()
        best = min(best, (time.perf_counter() - t0) / reps)
    return best


def ns_per_node_step(plant, batch: int, repeats: int, budget_s: float = 0.3) -> float:
    """Best-of-`repeats` time of one step of a batch, per node and run [ns]."""
    rng = np.random.default_rng(0)
    X = plant.initial_state(batch) + 0.1 * rng.standard_normal((batch, plant.n_x))
    U = np.full((batch, plant.n_u), 0.1)
    return best_seconds(lambda: plant.step(X, U), repeats, budget_s) / (batch * plant.n_x) * 1e9


def me_floor(plant, X: np.ndarray, U: np.ndarray):
    """The C calls of one Model Exchange step of the batch, alone: per RK4 stage and run, set
    states, set inputs, get derivatives (the stepper's prebuilt arguments, no arithmetic)."""
    st = plant._stepper
    ws = st.workspace(X.shape[0])
    ws.T[...], ws.V[...] = X, U
    b = st.b
    sx, sv, gd = b.set_states, b.set_reals, b.get_derivatives
    stages = 4 * st.substeps

    def run():
        for _ in range(stages):
            for a, v, d in zip(ws.on_T, ws.inputs, ws.into_K[0]):
                sx(*a)
                sv(*v)
                gd(*d)

    def run_shared():                                # one input row: set once per step, as sep does
        sv(*ws.inputs[0])
        for _ in range(stages):
            for a, d in zip(ws.on_T, ws.into_K[0]):
                sx(*a)
                gd(*d)
    return run_shared if U.shape[0] == 1 else run


def cs_floor(plant, X: np.ndarray, U: np.ndarray):
    """The C calls of one Co-Simulation step of the batch, alone (the stepper's prebuilt
    arguments; no checks, no checksums, no encoding)."""
    st = plant._stepper
    b = st.b
    M = X.shape[0]
    ws = st.workspace(M)
    raw, sizes = st._unpack(X)
    ws.raw[...], ws.V[...] = raw, U
    for m in range(M):
        ws.sizes[m].value, ws.times[m].value = int(sizes[m]), X[m, 2]
    h_in = st._in_state

    def run():
        for m in range(M):
            b.deserialize(*ws.load[m])
            b.set_state(b.c, h_in)
            b.set_reals(*ws.inputs[m])
            b.do_step(*ws.steps[m])
            b.get_reals(*ws.outs[m])
            b.get_state(*ws.get_state)
            b.state_size(*ws.size_of)
            b.serialize(*ws.save[m])
    return run


def do_step_alone(plant, M: int):
    """M fmiDoStep calls of the FMU's own RK4 from one state (its integration in C)."""
    from ctypes import c_double, c_void_p

    st = plant._stepper
    b = st.b
    X0 = plant.initial_state(1)
    raw, sizes = st._unpack(X0)
    load = (b.c, c_void_p(raw.ctypes.data), c_size_t(int(sizes[0])), byref(st._in_state))
    t = c_double(0.0)
    args = b.step_args(t, st._h)

    def run():                                       # from the initial state (other calls move the FMU)
        status = b.deserialize(*load) | b.set_state(b.c, st._in_state)
        t.value = X0[0, 2]
        for _ in range(M):
            status |= b.do_step(*args)
            t.value += st.dt
        assert status <= 1, "fmiDoStep failed"
        assert raw is not None
    return run


def alternating(fns: list, repeats: int, rounds: int = 3) -> list[float]:
    """Best seconds of each function, measured in alternating rounds (a shared machine's load
    then hits them alike)."""
    best = [np.inf] * len(fns)
    for _ in range(rounds):
        for i, fn in enumerate(fns):
            best[i] = min(best[i], best_seconds(fn, repeats, budget_s=0.15))
    return best


def rod_module():
    """tests/fmu_rod.py: the native rod and the build of its FMUs (examples/fmu_rod/build_fmu.py)."""
    if str(ROOT / "tests") not in sys.path:
        sys.path.insert(0, str(ROOT / "tests"))
    import fmu_rod

    return fmu_rod


def build_rods(tmp: Path) -> dict[int, Path] | None:
    """The example rod FMU built into `tmp` for FMI 2.0 and 3.0, each compiled once for the
    cost and the design tables; None without a C compiler."""
    rod = rod_module()
    if rod.compiler() is None:
        return None
    return {v: rod.build(tmp / f"rod{v}.fmu", fmi_version=v) for v in (2, 3)}


def fmu_plants(rods: dict[int, Path]):
    """(label, plant, floor) of the native rod and the rod FMUs `rods` (FMI 2.0 and 3.0, ME and CS)."""
    keys = {"inputs": ["heater_1", "heater_2", "heater_3"], "field": "T"}
    plants = [("native rod (numpy RK4)", rod_module().RodPlant(), None)]
    for v, fmu in rods.items():
        path = str(fmu)
        plants.append((f"FMI {v}.0 ME (sep RK4)", make_plant("fmu", {"path": path, **keys, "substeps": 4}), me_floor))
        plants.append((f"FMI {v}.0 CS (FMU RK4)", make_plant("fmu", {"path": path, **keys, "interface": "co_simulation"}),
                       cs_floor))
    return plants


def fmu_row(label: str, p, floor, M: int, U: np.ndarray, repeats: int) -> tuple[list[str], tuple]:
    """One row: sep's step, the same FMU calls alone, doStep alone (CS) [s per batch step]."""
    opaque = getattr(p, "state_is_opaque", False)
    X = p.initial_state(M)
    X = p.step(X, U) if opaque else X
    fns = [lambda: p.step(X, U)] + ([floor(p, X, U)] if floor else []) + ([do_step_alone(p, M)] if opaque else [])
    t = alternating(fns, repeats) + [None, None]
    ns = [None if v is None else f"{v / (M * 50) * 1e9:.0f}" for v in t]
    row = [label, str(p.n_x), str(M), f"{t[0] / M * 1e6:.1f}", ns[0], ns[1] or "-",
           f"{t[0] / t[1]:.2f}x" if t[1] else "-", ns[2] or "-"]
    return row, (label, t[0] / M, None if t[1] is None else t[1] / M, None if t[2] is None else t[2] / M)


def fmu_tables(repeats: int, designs: bool) -> None:
    """The FMU cost table, and with `designs` the design table, of the example rod built once."""
    with tempfile.TemporaryDirectory() as tmp:
        rods = build_rods(Path(tmp))
        if rods is None:
            print("\nFMU plants: skipped (no C compiler to build examples/fmu_rod)")
            return
        fmu_table(repeats, rods)
        if designs:
            fmu_design_table(rods[2])


def fmu_table(repeats: int, rods: dict[int, Path]) -> None:
    """Cost of the FMU plants `rods` next to the native rod and their floors (module docstring)."""
    rows, where = [], []
    plants = fmu_plants(rods)
    rng = np.random.default_rng(0)
    for M in FMU_BATCHES:
        U = 0.3 + 0.05 * rng.standard_normal((M, 3))
        for label, p, floor in plants:
            row, times = fmu_row(label, p, floor, M, U, repeats)
            rows.append(row)
            if M == 64 and floor is not None:
                where.append(times)
        print(f"FMU table: M = {M} done", file=sys.stderr, flush=True)
    print_table(f"FMU plants: the example rod (50 nodes, dt 0.25 s, RK4 4 substeps) [best of {repeats}; one core]; "
                "floor = the same FMU calls alone in a tight loop",
                ["plant", "n_x", "M", "us/run-step", "ns/node-step", "FMU calls alone (floor)", "sep / floor",
                 "doStep alone"], rows)
    c_eval = next((c / 16 for *_, c in where if c is not None), None)   # 4 substeps x 4 stages per doStep
    for label, sep, floor, c in where:
        if c is not None:
            print(f"  {label}, M = 64, per run-step: {sep * 1e6:.1f} us = the FMU's own RK4 in C {c * 1e6:.1f} us "
                  f"+ ctypes overhead of its 8 FMI calls {(floor - c) * 1e6:.1f} us + sep's Python/numpy "
                  f"(checksums, encoding) {(sep - floor) * 1e6:.1f} us")
        elif c_eval is not None:
            over = floor - 16 * c_eval
            print(f"  {label}, M = 64, per run-step: {sep * 1e6:.1f} us = 16 derivative evaluations in C "
                  f"~{16 * c_eval * 1e6:.1f} us + ctypes overhead of 48 FMI calls ~{over * 1e6:.1f} us "
                  f"({over / 48 * 1e9:.0f} ns per call) + sep's RK4 arithmetic (numpy) {(sep - floor) * 1e6:.1f} us")


def rod_scenarios(fmu: Path) -> dict:
    """The example scenario (examples/fmu_rod/scenario.yaml) with the FMU `fmu` as Model
    Exchange and Co-Simulation plant, and with the native rod of the same outputs (sensor
    positions: the FMU's defaults, build_fmu.PARAMETERS)."""
    from sep_plant.scenario import Scenario, load_scenario

    text = (ROOT / "examples" / "fmu_rod" / "scenario.yaml").read_text()
    folder = fmu.parent
    (folder / "me.yaml").write_text(text.replace("path: rod.fmu", f"path: {fmu.name}"))
    cs = text.replace("path: rod.fmu", f"path: {fmu.name}").replace("interface: model_exchange", "interface: co_simulation")
    (folder / "cs.yaml").write_text("\n".join(line for line in cs.splitlines() if not line.lstrip().startswith("substeps:")))
    me = load_scenario(folder / "me.yaml")
    plant = me.plant
    position = {name.replace("_position", ""): start for name, start, *_ in rod_module().build_module().PARAMETERS}
    native = Scenario("fmu_rod:RodPlant", {"t_right": 120.0, "substeps": plant.substeps, "dt": plant.dt,
                                           "sensor_positions": [position[n] for n in plant.output_names]},
                      me.problem).canonical()
    return {"native rod (numpy RK4)": native, "FMI 2.0 ME (sep RK4)": me, "FMI 2.0 CS (FMU RK4)": load_scenario(folder / "cs.yaml")}


def fmu_design_table(fmu: Path) -> None:
    """Whole designs of the example scenario with the FMI 2.0 rod `fmu`: native rod, ME and CS
    FMU, and ME on --dask local:2."""
    from sep_control.compute.engine import open_engine
    from sep_control.design.pipeline import DesignSettings, run_design

    scenarios = rod_scenarios(fmu)
    quiet = {"show_progress": False, "log": lambda m: None}
    rows, designs = [], {}
    for label, sc in scenarios.items():
        t0 = time.perf_counter()
        d = designs[label] = run_design(sc.plant, sc.problem, DesignSettings.for_scenario(sc), **quiet)
        wall = time.perf_counter() - t0
        t, opt = d.meta["timings"], d.meta["optimizer"]
        rows.append([label, str(sc.plant.n_x), f"{wall:.1f}", f"{t['optimize_s']:.1f}", f"{t['identify_s']:.1f}",
                     f"{opt['experiments'] + opt['belief_experiments']}", d.meta["belief"],
                     f"{opt['nominal_cost']:.8g}"])
        print(f"FMU designs: {label} done", file=sys.stderr, flush=True)
    ref = designs["native rod (numpy RK4)"].meta["optimizer"]["nominal_cost"]
    for row, d in zip(rows, designs.values()):
        row.append(f"{abs(d.meta['optimizer']['nominal_cost'] - ref) / ref:.1e}")
    print_table("Designs of examples/fmu_rod/scenario.yaml [s; default settings, in-process, one core]",
                ["plant", "n_x", "design s", "optimize s", "identify s", "experiments", "belief",
                 "nominal cost", "vs native (rel)"], rows)
    me_label = "FMI 2.0 ME (sep RK4)"
    me, here = scenarios[me_label], designs[me_label]
    with open_engine("local:2") as eng:
        t0 = time.perf_counter()
        there = run_design(me.plant, me.problem, DesignSettings.for_scenario(me), engine=eng, **quiet)
        wall = time.perf_counter() - t0
        scattered = eng.files_scattered
    diff = max(float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300)) for a, b in (
        (there.nominal.u, here.nominal.u), (there.lqg.K, here.lqg.K), (there.lqg.field_std, here.lqg.field_std),
        (there.rom.C, here.rom.C), (there.hankel_sv, here.hankel_sv)))
    print(f"  {me_label} on --dask local:2: design {wall:.1f} s, largest relative difference from in-process "
          f"(u_nom, K, field_std, C, Hankel SVs) {diff:.1e}, the FMU's bytes scattered {scattered} time(s)")


def device_row(label: str, kind: str, cfg: dict, batch: int, xp, repeats: int) -> list[str]:
    """One row of the device table: CPU vs device (round trip, resident) [ns per node-step]."""
    cpu = make_plant(kind, cfg)
    dev = DevicePlant(cpu, xp, "cuda")
    rng = np.random.default_rng(0)
    X = cpu.initial_state(batch) + 0.1 * rng.standard_normal((batch, cpu.n_x))
    U = np.full((batch, cpu.n_u), 0.1)
    ref = cpu.step(X, U)
    diff = np.max(np.abs(dev.step(X, U) - ref)) / max(np.max(np.abs(ref - X)), 1e-300)
    t_cpu = ns_per_node_step(cpu, batch, max(1, min(repeats, 2)))
    t_trip = ns_per_node_step(dev, batch, repeats)

    class Resident:                        # the state stays on the device; float() waits for the step
        n_x, n_u = cpu.n_x, cpu.n_u
        Xd, Ud = xp.asarray(X), xp.asarray(U)

        def initial_state(self, b):
            return X

        def step(self, _x, _u):
            out = dev.plant.step(self.Xd, self.Ud)
            float(out[0, 0])
            return out

    t_res = ns_per_node_step(Resident(), batch, repeats)
    return [label, str(cpu.n_x), str(batch), f"{t_cpu:.1f}", f"{t_trip:.2f}", f"{t_cpu / t_trip:.1f}x",
            f"{t_res:.2f}", f"{t_cpu / t_res:.1f}x", f"{diff:.1e}"]


def rollout(plant, x, u, steps: int) -> np.ndarray:
    for _ in range(steps):
        x = plant.step(x, u)
    return x


def rk4(plant, x, u, horizon: float, h: float):
    """The semi-discrete system (plant.rhs) integrated by classical RK4 with small steps."""
    return adi.rk4(plant.rhs, x, u, horizon, h)


def rk4_step_size(plant, fields: np.ndarray) -> float:
    """Half of RK4's real-axis stability limit 2.78 / lambda_max: a Gershgorin bound of the
    diffusion at the largest conductivity over `fields` (+10 %), plus the loss or reaction."""
    if hasattr(plant, "k0"):
        T = np.array([fields.min(), fields.max()])
        K = 1.1 * float(np.max(plant.k0 * (1 + plant.beta * (T - plant.t_ref) / plant.t_scale)))
        extra = plant.eta + 4 * plant.radiation * float(np.max(plant._kelvin(T))) ** 3
    else:
        K, extra = plant.eps ** 2, 2.0
    lam = sum(4.0 * K / h**2 for h in plant.grid.h) + extra
    return 0.5 * 2.78 / lam


def relative_errors(x: np.ndarray, ref: np.ndarray, x0: np.ndarray) -> tuple[float, float]:
    change = np.abs(ref - x0).max()
    return float(np.abs(x - ref).max() / change), float(np.sqrt(np.mean((x - ref) ** 2)) / change)


def accuracy(kind: str, cfg: dict, u: float, horizon: float, with_rk4: bool) -> list[str]:
    """[max change, Richardson max, rms, RK4 max, rms, RK4 vs Richardson] as strings."""
    p = make_plant(kind, cfg)
    x0 = p.initial_state(1)
    U = np.full(p.n_u, u)
    steps = int(round(horizon / p.dt))
    x = rollout(p, x0, U, steps)
    fine = {m: rollout(make_plant(kind, {**cfg, "dt": p.dt / m}), x0, U, steps * m) for m in (64, 128)}
    richardson = 2.0 * fine[128] - fine[64]
    e_max, e_rms = relative_errors(x, richardson, x0)
    row = [f"{np.abs(richardson - x0).max():.3g}", f"{e_max:.2e}", f"{e_rms:.2e}"]
    if not with_rk4:
        return row + ["-", "-", "-"]
    ref = rk4(p, x0, U, horizon, rk4_step_size(p, np.concatenate([x0, richardson])))
    r_max, r_rms = relative_errors(x, ref, x0)
    return row + [f"{r_max:.2e}", f"{r_rms:.2e}", f"{np.abs(ref - richardson).max() / np.abs(ref - x0).max():.1e}"]


def print_table(title: str, header: list[str], rows: list[list[str]]) -> None:
    widths = [max(len(str(r[i])) for r in [header] + rows) for i in range(len(header))]
    print(f"\n{title}")
    print("| " + " | ".join(h.ljust(w) for h, w in zip(header, widths)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        print("| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timing repeats (best is reported)")
    ap.add_argument("--horizon", type=float, default=10.0, help="accuracy horizon [s]")
    ap.add_argument("--solvers", action="store_true", help="also compare the line solvers")
    ap.add_argument("--blocks", action="store_true", help="also compare block sizes of large batches")
    ap.add_argument("--only-blocks", action="store_true", help="the block table alone")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="cuda: also the table of batched steps on the GPU (CuPy)")
    ap.add_argument("--only-device", action="store_true", help="the device table alone")
    ap.add_argument("--only-fmu", action="store_true", help="the FMU plants' table alone")
    args = ap.parse_args()
    if args.only_fmu:
        fmu_tables(args.repeats, designs=True)
        return
    args.blocks = args.blocks or args.only_blocks
    if args.only_device and args.device == "cpu":
        ap.error("--only-device needs --device cuda")
    if args.only_device:
        args.only_blocks = True
        args.blocks = False

    rows = []
    for label, kind, cfg, batches, u, with_rk4 in ([] if args.only_blocks else CASES):
        p = make_plant(kind, cfg)
        cost = {b: ns_per_node_step(p, b, args.repeats) for b in batches}
        rows.append([label, str(p.n_x), f"{p.dt:g}"]
                    + [f"{cost[b]:.1f}" if b in cost else "-" for b in (1, 64, 200)]
                    + [f"{cost[1] * p.n_x * 1e-6:.3f}"] + accuracy(kind, cfg, u, args.horizon, with_rk4))
    if rows:
        print_table(f"Cost [ns per node-step of one batched step; one core, best of {args.repeats}] and accuracy at the "
                    f"default dt after {args.horizon:g} s (error / largest change of the field)",
                    ["plant", "n_x", "dt [s]", "M = 1", "M = 64", "M = 200", "ms/step M=1", "max change",
                     "vs Richardson max", "rms", "vs RK4 max", "rms", "RK4 vs Richardson"], rows)

    if args.solvers:
        rows = []
        for label, kind, cfg, *_ in CASES:
            if kind == "slab":
                continue
            p = make_plant(kind, cfg)
            row = [label]
            for batch in (1, 64):
                for solver in ("auto", "lapack", "thomas", "pcr"):
                    p.solver = solver
                    row.append(f"{ns_per_node_step(p, batch, args.repeats):.1f}")
            rows.append(row)
        print_table("Line solvers [ns per node-step]: auto (dptsv on the last axis, Thomas on the others from "
                    "2048 lines), lapack (dptsv on every axis), thomas (Thomas on every axis), pcr (parallel "
                    "cyclic reduction on every axis)",
                    ["plant"] + [f"M={m} {s}" for m in (1, 64) for s in ("auto", "lapack", "thomas", "pcr")], rows)

    if args.blocks:
        rows = []
        for label, kind, cfg, batch in BLOCK_CASES:
            p = make_plant(kind, cfg)
            p.block_nodes = batch * p.n_x                                  # one piece
            whole = ns_per_node_step(p, batch, args.repeats)
            row = [label, str(p.n_x), str(batch), f"{whole:.1f}"]
            for k in BLOCK_SIZES:
                p.block_nodes = 1 << k
                t = ns_per_node_step(p, batch, args.repeats)
                row.append(f"{t:.1f} ({whole / t:.2f}x)")
            rows.append(row)
            print(" | ".join(row), flush=True)
        default = blocks.BLOCK_NODES.bit_length() - 1
        print_table(f"Batch in blocks [ns per node-step; (speed-up over one piece)]; default block 2^{default} nodes",
                    ["plant", "n_x", "runs", "one piece"]
                    + [f"2^{k}{' (default)' if k == default else ''}" for k in BLOCK_SIZES], rows)

    if not args.only_blocks:
        fmu_tables(args.repeats, designs=False)

    if args.device != "cpu":
        xp = array_module(args.device)
        rows = []
        for case in DEVICE_CASES:
            rows.append(device_row(*case, xp, args.repeats))
            print(" | ".join(rows[-1]), flush=True)
        print_table(f"Batched steps on {args.device} [ns per node-step]: one CPU core vs the device with the "
                    "state's round trip (--device cuda) and resident on the device; max |device - CPU| / "
                    "max |step change|", ["plant", "n_x", "runs", "CPU", "device (round trip)", "speed-up",
                                          "device (resident)", "speed-up", "difference"], rows)


if __name__ == "__main__":
    main()
