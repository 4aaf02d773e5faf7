"""`sep design`: the offline design tool (scenario in, design file out)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from typing import Any

from sep_estimator.design_file import save_design
from sep_estimator.disturbance import KINDS as DISTURBANCE_KINDS
from sep_estimator.disturbance import STD0_BANDS, DisturbanceError
from sep_estimator.disturbance import summary as disturbance_summary

from sep_control.cli.common import (add_compute_options, add_deprecated, blas_threads, engine_or_exit, fail, groups,
                                    legacy_main, memory_budget_or_exit, plant_or_exit, scenario_or_exit, stderr_log)
from sep_control.compute.progress import bars_wanted
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.design.plan import format_run_steps

HELP = "design a data-driven LQG for a plant (scenario in, design file out)"
DESCRIPTION = """\
Design a data-driven LQG for a plant (the heat slab by default; any plant of the plant
protocol through --scenario) from the black-box simulator only:
  1. optimize the open-loop nominal (Gauss-Newton/LM, its Jacobian from a TV-ERA model or from
     impulse sensitivities, both from batched experiments; then refine it in belief space with
     an EnKF belief; a plant whose states are opaque, e.g. a Co-Simulation FMU, keeps the
     mean-only nominal and has no belief),
  2. identify the reduced-order LTV model with TV-ERA (and the field map on a POD basis),
  3. design the time-varying LQR and Kalman filter on the ROM,
and write everything to one design file (.npz, read without pickles; docs/reference/design-file.md),
with a record of everything it was made from.

With no --scenario the shipped reference scenario (docs/method.md) is used. The plant is
checked against the plant protocol first (exit 2 with what to fix).
Examples: sep design --out out/design.npz
          sep design --scenario sep_plant/scenarios/plate.yaml --out out/plate.npz
"""

#: DesignSettings keys of the flags whose setting has another name (none today; one table for renames)
SETTING_KEY = {"enkf_seed": "enkf_seed"}

#: command-line options of DesignSettings keys: (flag, settings key, type/action, help, basic)
SETTINGS_OPTIONS = (
    ("--n-r", "n_r", dict(type=int), "ROM order cap n_r", True),
    ("--ensemble", "ensemble", dict(type=int), "EnKF members (even)", True),
    ("--enkf-seed", SETTING_KEY["enkf_seed"], dict(type=int), "EnKF random seed", True),
    ("--max-iter", "max_iter", dict(type=int), "optimizer iterations", True),
    ("--method", "method", dict(choices=["gn", "gd"]),
     "optimizer: gn = Gauss-Newton/Levenberg-Marquardt, gd = the paper's gradient descent", False),
    ("--jacobian", "jacobian", dict(choices=["auto", "sensitivity", "rom"]),
     "Gauss-Newton Jacobian: sensitivity = N n_u impulse-sensitivity experiments per iteration and a "
     "dense (N n_u)^2 step; rom = a TV-ERA model identified per iteration (see --relinearize-rtol), the "
     "step solved on it by a Riccati pass (its last identification is the design's ROM when made at the "
     "final input); auto = rom when N + 1 > 5 (p + q), "
     "where it is measured faster, or when the sensitivity batch would not fit the memory budget, else "
     "sensitivity until a step moves the input by 1 %% or less or lowers the cost by 1e-3 or less, and rom "
     "from there (one identification near the optimum, which the belief refinement and the design reuse)", False),
    ("--relinearize-rtol", "relinearize_rtol", dict(type=float),
     "rom Jacobian: keep the last identification for the next step while the input moved by less than "
     "this, relative (max |dU| / max |U|, at most 0.1; near the optimum the steps move U by 1e-3 and less). The "
     "design's ROM is always identified at the final input (afresh, or the optimizer's last model when "
     "made there); 1e-6 identifies after every step", False),
    ("--tol", "tol", dict(type=float),
     "stop when an accepted trial lowers the cost by less than this, relative (that step is not taken); the "
     "belief refinement also stops, without the trial's EnKF run, when the Gauss-Newton model predicts less", False),
    ("--step-size", "step_size", dict(type=float), "gradient-descent step alpha", False),
    ("--belief-iter", "belief_iter", dict(type=int), "belief-space GN iterations", False),
    ("--p", "p", dict(type=int), "Hankel block rows (future outputs)", False),
    ("--q", "q", dict(type=int), "Hankel block columns (past inputs)", False),
    ("--sv-tol", "sv_tol", dict(type=float), "relative Hankel singular-value cutoff", False),
    ("--impulse", "impulse", dict(type=float), "impulse amplitude relative to the RMS nominal input", False),
    ("--field-tol", "field_tol", dict(type=float),
     "the identifications' field basis (POD of the field responses, streamed) keeps the directions above this "
     "times the largest response; its projections are the "
     "design's main work outside the plant step on large grids (4 n_f r flops per snapshot, r the basis rank)",
     False),
    ("--field-map-tol", "field_map_tol", dict(type=float),
     "the design's field map G_k = Phi g_k keeps the directions that move the field by more than this times "
     "its largest spread (the ROM state's covariance with and without the feedback); what is dropped changes the "
     "reconstructed field and its std by about that much (measured: <= 9.3e-4 of the largest std at 1e-5). The "
     "gains do not use the map. Smaller keeps more of Phi: a larger file and a slower online reconstruction",
     False),
    ("--impulse-scheme", "impulse_scheme", dict(choices=["central", "forward"]),
     "TV-ERA impulse experiments: central = +- pairs (no first-order bias); forward = one run per "
     "impulse against an unperturbed copy in the same batch (about half the plant steps, a bias "
     "of O(amplitude): 4e-6 relative in the reference's Markov parameters at --impulse 0.01; a "
     "smaller amplitude trades the bias for round-off in the field map, see docs/method.md)", False),
    ("--impulse-stride", "impulse_stride", dict(type=int),
     "TV-ERA impulses at every stride-th start step (and the last); the Markov parameters of the start steps "
     "between are interpolated linearly (about 1/stride of the identification's plant steps; default: the "
     "plan's, 1 for 0.8, 2 for 0.9; the design logs the Markov error of its model, and identifies its final model "
     "again at every start step where the strided data resolve under half of the ROM's kept states)", False),
    ("--experiment-plan", "experiment_plan", dict(choices=["0.8", "0.9"]),
     "which experiments the design runs: 0.9 (the default) = a coarse first model kept while its steps pay, "
     "forward impulses at every second start step, a settle stop, a spot check before the optimizer's last model "
     "is reused, no belief refinement, 50 EnKF members, the clip correction under input or rate limits "
     "(0.17-0.21x sep 0.8.0's plant run-steps on the reference, plate, rod and Burgers; docs/benchmarks.md); "
     "0.8 = sep 0.8.0's plan (its designs bit for bit)", False),
    ("--chunks", "chunks", dict(type=int),
     "TV-ERA impulse experiments in this many chunks of start steps (tasks for --dask). The chunks "
     "fix how the field basis is merged, so the design depends on --chunks (at the field basis' "
     "tolerance) but never on --dask; use at least twice the cluster's workers", False),
    ("--limit-margin", "limit_margin", dict(type=float),
     "with input limits: re-optimize the nominal inside u_min + c sigma_u, u_max - c sigma_u (sigma_u: the "
     "designed LQG's closed-loop input std) so the feedback has room; 0 = none. On the reference with "
     "u in [0, 0.6] any c that binds costs the band (docs/robustness.md)", False),
    ("--margin-iterations", "margin_iterations", dict(type=int), "nominal + LQG redesigns with the margin", False),
    ("--clip-correction", "clip_correction", dict(type=lambda text: _on_off(text), metavar="{on,off}"),
     "with input or rate limits: move the nominal to where a Monte Carlo of the closed loop on the ROM (no plant steps) "
     "predicts the lowest cost with the limits clipping the feedback, then identify and design again there "
     "(kept only when the ROM predicts it cheaper; the FMU rod: ROM-LQG cost 9.74 -> 8.08, docs/method.md)", False),
    ("--fd-eps", "fd_eps", dict(type=float), "sensitivity experiment amplitude", False),
    ("--disturbance", "disturbance", dict(choices=list(DISTURBANCE_KINDS[1:]) + ["none"]),
     "disturbance states of the ROM filter for offset-free tracking (docs/method.md): input = constant input "
     "biases along the input directions the sensors detect (the right singular vectors of the ROM's band-window "
     "step gain; a boundary, ambient or heater offset), removed by the LQR; noise = constant forcings where the "
     "process noise enters (its own channels: a distributed source; the input kind when the noise is on the "
     "inputs); output = one bias per sensor, removed from the estimate; input+noise, noise+output, input+output = "
     "two kinds' states stacked, n_d <= n_y split between them (docs/robustness.md); none = the plain LQG", True),
    ("--disturbance-std", "disturbance_std", dict(type=float, nargs="+"),
     "prior std of the disturbances: one number, or one per direction (default: c band / sqrt(S_i S_cl,i), a bias "
     f"moving the outputs by c = {STD0_BANDS:g} bands along direction i, S_i and S_cl,i its open-loop and "
     "plain-LQR closed-loop step gains; output kind: c band)", False),
    ("--disturbance-dims", "disturbance_dims", dict(type=int, nargs="+"),
     "number of disturbance states n_d, at most n_y (input default: min(n_y, n_u); output: n_y); a combination: "
     "two numbers, n_d per part, n_1 + n_2 <= n_y (default ceil(n_y / 2) for the first part, the rest for the "
     "second)", False),
    ("--disturbance-walk-std", "disturbance_walk_std", dict(type=float, nargs="+"),
     "random-walk std of the disturbances per step: one number, or one per direction (0: constant biases)",
     False),
)
#: on/off settings: (flag, settings key, help, basic)
SWITCH_OPTIONS = (
    ("--no-belief", "belief", "skip the belief-space refinement (mean-only nominal)", True),
    ("--no-coarse-proposals", "coarse_proposals",
     "rom Jacobian: identify every model with the full settings; by default the identifications far from the "
     "optimum, which only propose Gauss-Newton steps, use forward impulses and a field basis to 1e-6 (about half "
     "the plant steps; plan 0.9: Hankel blocks p = q = 8 as well), and the ones near it and the design's ROM the "
     "full ones", False),
)
_DEFAULT_TEXT = {"max_iter": "10 for gn, 60 for gd", "clip_correction": "the plan's: off for 0.8, on for 0.9",
                 "field_tol": "the plan's: 1e-8 for 0.8, 1e-6 for 0.9"}


def _on_off(text: str) -> bool:
    """'on' -> True, 'off' -> False (argparse type)."""
    if text not in ("on", "off"):
        raise argparse.ArgumentTypeError(f"expected on or off, got {text!r}")
    return text == "on"
_DEST = "setting_"       # argparse dest prefix of the settings (apart from a demo's own --seed)


def configure(parser: argparse.ArgumentParser) -> None:
    """The options of `sep design`."""
    basic, advanced = groups(parser)
    basic.add_argument("--scenario", metavar="FILE",
                       help="scenario YAML: a `plant:` section (type and keys), the problem keys that differ from "
                            "the defaults (a file of problem keys only means the reference plant) and optionally "
                            "a `design:` section with this scenario's defaults for the options below "
                            "(docs/plants.md)")
    basic.add_argument("--out", metavar="DESIGN_FILE", required=True, help="design file to write (.npz)")
    basic.add_argument("--json", metavar="PATH", help="also write the design summary as JSON")
    basic.add_argument("--quiet", action="store_true",
                       help="no progress bars and no log lines but warnings (bars are drawn only when stderr is a terminal)")
    add_design_options(basic, advanced)
    add_deprecated(advanced, "--seed", "--enkf-seed", _DEST + SETTING_KEY["enkf_seed"], type=int)
    add_compute_options(advanced)


def add_design_options(basic, advanced) -> None:
    """The DesignSettings options (`SETTINGS_OPTIONS`, `SWITCH_OPTIONS`), shared with `sep demo`.
    An option not given leaves the setting to the scenario's `design:` section, else the default."""
    d = DesignSettings()
    for flag, key, kind, text, is_basic in SETTINGS_OPTIONS:
        meta = {} if "choices" in kind or "metavar" in kind else {"metavar": flag.lstrip("-").replace("-", "_").upper()}
        default = _DEFAULT_TEXT.get(key, getattr(d, key))
        (basic if is_basic else advanced).add_argument(
            flag, dest=_DEST + key, default=argparse.SUPPRESS, **meta, **kind,
            help=f"{text} (default: the scenario's design section, else {default})")
    for flag, key, text, is_basic in SWITCH_OPTIONS:
        (basic if is_basic else advanced).add_argument(flag, dest=_DEST + key, action="store_false",
                                                       default=argparse.SUPPRESS, help=text)


def settings_from_args(args: argparse.Namespace, scenario) -> DesignSettings:
    """DesignSettings: the defaults, the scenario's `design:` section, then the options given
    (exit 2 naming a bad value)."""
    given = {k[len(_DEST):]: v for k, v in vars(args).items() if k.startswith(_DEST)}
    for key in ("disturbance_std", "disturbance_walk_std"):      # one number: for every direction
        if isinstance(given.get(key), list) and len(given[key]) == 1:
            given[key] = given[key][0]
    if isinstance(given.get("disturbance_dims"), list) and len(given["disturbance_dims"]) == 1:
        given["disturbance_dims"] = given["disturbance_dims"][0]
    try:
        return DesignSettings.for_scenario(scenario, memory_budget=memory_budget_or_exit(args.memory_budget),
                                           **given)
    except (ValueError, TypeError) as exc:
        fail(str(exc))


def settings_fit_or_exit(settings: DesignSettings, plant) -> None:
    """Exit 2 naming the key when the settings do not fit the plant (`DesignSettings.check_plant_dims`:
    disturbance_dims > n_y, lists of the wrong length)."""
    try:
        settings.check_plant_dims(int(plant.n_u), int(plant.n_y))
    except ValueError as exc:
        fail(str(exc))


def recorded_settings(settings: DesignSettings, plant, n_steps: int) -> dict[str, Any]:
    """The settings as a design made with them records them in its source record
    (`sep_estimator.design_source.source_differences`): every setting and the Jacobian 'auto'
    resolves to for this plant and horizon (belief off for a plant with opaque states,
    `DesignSettings.for_plant`)."""
    return {**asdict(settings.for_plant(plant)), "jacobian_used": settings.resolved_jacobian_for(plant, n_steps)}


def make_design(plant, scenario, settings: DesignSettings, args: argparse.Namespace, log, show_progress: bool):
    """`run_design` with the compute options of `args` (--threads, --dask); a disturbance model
    that does not fit the identified ROM (DisturbanceError) exits 2 with its message."""
    with blas_threads(args.threads), engine_or_exit(args.dask, log=stderr_log()) as engine:
        try:
            return run_design(plant, scenario.problem, settings, show_progress=show_progress, log=log, engine=engine)
        except DisturbanceError as exc:
            fail(f"the disturbance model does not fit this plant: {exc}")


def run(args: argparse.Namespace) -> int:
    scenario = scenario_or_exit(args.scenario)
    settings = settings_from_args(args, scenario)
    log = stderr_log(args.quiet)
    plant = plant_or_exit(scenario, args.scenario or "reference scenario", device=args.device)
    settings_fit_or_exit(settings, plant)
    log(f"design: scenario {args.scenario or '(reference)'}: plant {scenario.plant_type}, n_x = {plant.n_x}, "
        f"n_field = {plant.n_field}, N = {scenario.problem.n_steps}, dt = {plant.dt} s, {plant.n_u} inputs, "
        f"{plant.n_y} outputs, plant steps on {args.device}")
    t0 = time.perf_counter()
    design = make_design(plant, scenario, settings, args, log, show_progress=bars_wanted(args.quiet))
    path = save_design(args.out, design)
    summary = design_summary(design)
    summary["wall_s"] = time.perf_counter() - t0
    print(format_summary(summary, str(path)))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(summary, fh, indent=2)
    return 0


def design_summary(design) -> dict:
    m, info = design.meta, design.info
    return {
        "plant": design.scenario.plant_type, "n_x": info.n_x, "n_field": info.n_field,
        "n_steps": design.n_steps, "n_r": int(design.rom.dims.max()),
        "disturbance": disturbance_summary(design.disturbance),
        "nominal_cost": m["optimizer"]["nominal_cost"],
        "mean_only_cost": m["optimizer"]["mean_only_cost"],
        "belief_history": m["optimizer"]["belief_history"],
        "max_dev_in_band_window": m["validation"]["max_dev_in_band_window"],
        "max_dev_per_hold": m["validation"].get("max_dev_per_hold"),     # a recipe's holds
        "hold_bands": [b for _, _, b in design.objective.holds] if design.objective.holds else None,
        "markov_rel_error": m["validation"]["markov_rel_error"],
        # strided impulses: the share of the kept ROM states they resolve (`stride_check`; None: every start step)
        "stride_resolved_share": m["validation"].get("stride_resolved_share"),
        "timings": m["timings"],
        "run_steps": m.get("run_steps"),              # plant run-steps per stage (None: files before 0.9)
        "clip_correction": m.get("clip_correction"),  # what the clip correction predicted and kept (None: not run)
        "experiment_plan": m.get("settings", {}).get("experiment_plan", "0.8"),
        "source_digest": m.get("source_digest"),     # set by save_design
    }


def format_summary(sm: dict, path: str) -> str:
    t = sm["timings"]
    lines = [
        f"design written to {path}",
        f"  nominal cost J           {sm['nominal_cost']:.6g}  (mean-only optimum {sm['mean_only_cost']:.6g})",
        f"  nominal max |f - f*|     {sm['max_dev_in_band_window']:.3g} over the band window",
        *([f"  nominal max |f - f*|     per hold: " + ", ".join(
            f"{d:.3g} (band {b:g})" for d, b in zip(sm["max_dev_per_hold"], sm["hold_bands"]))]
          if sm.get("max_dev_per_hold") else []),
        f"  ROM order                n_r = {sm['n_r']}",
        f"  disturbance states       {sm['disturbance']}",
        f"  Markov relative error    {sm['markov_rel_error']:.2e}",
        f"  time                     optimize {t['optimize_s']:.2f} s, identify {t['identify_s']:.2f} s, "
        f"gains {t['gains_s']:.2f} s, "
        + (f"clip correction {t['clip_correction_s']:.2f} s, " if "clip_correction_s" in t else "")
        + f"total {t['total_s']:.2f} s",
    ]
    if sm.get("run_steps"):
        lines.append(f"  plant run-steps          {format_run_steps(sm['run_steps'])} "
                     f"(experiment plan {sm['experiment_plan']})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """The old `design` command: `sep design` with a deprecation line."""
    return legacy_main("design", argv)


if __name__ == "__main__":
    sys.exit(main())
