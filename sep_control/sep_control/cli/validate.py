"""`sep validate`: check a design's ROM against fresh experiments on the nonlinear simulator."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from sep_plant.noise import DEFAULT_SEED

from sep_control.cli.common import (add_compute_options, blas_threads, design_or_exit, engine_or_exit, fail, groups,
                                    legacy_main, plant_or_exit)
from sep_control.compute.progress import RunSteps, bars_wanted
from sep_control.evaluation.validation import validate, validation_run_steps

HELP = "check a design's reduced-order model against fresh experiments"
DESCRIPTION = """\
Validate the reduced-order model of a design file against the nonlinear plant (rebuilt from
the design file's scenario):
  markov     ROM Markov parameters C_k A_{k-1}..A_{j+1} B_j vs long central-difference
             impulse experiments (lags up to --lags, beyond the p+q used to identify);
  prediction ROM output and field prediction vs the nonlinear simulator for a random
             small input sequence du (noise-free), relative to the deviation itself.
Relative errors are Frobenius norms over all steps.

Example:  sep validate --design out/design.npz --json out/validate.json
"""


def configure(parser: argparse.ArgumentParser) -> None:
    """The options of `sep validate`."""
    basic, advanced = groups(parser)
    basic.add_argument("--design", metavar="DESIGN_FILE", required=True, help="design file from `sep design`")
    basic.add_argument("--json", metavar="PATH", help="write the errors as JSON")
    basic.add_argument("--quiet", action="store_true",
                       help="no progress bar (drawn in run-steps only when stderr is a terminal)")
    advanced.add_argument("--lags", type=int, default=60, help="impulse-response length for the Markov check")
    advanced.add_argument("--amplitude", type=float, default=0.01,
                          help="random input deviation std, relative to the RMS nominal input")
    advanced.add_argument("--seed", type=int, default=DEFAULT_SEED, help="seed of the random input deviation")
    add_compute_options(advanced, memory_budget=False)


def run(args: argparse.Namespace) -> int:
    if args.lags < 1 or not args.amplitude > 0:
        fail("--lags must be >= 1 and --amplitude > 0")
    design = design_or_exit(args.design)
    plant = plant_or_exit(design.scenario, f"{args.design} (its scenario)", device=args.device)
    total = validation_run_steps(plant, design.n_steps, args.lags)
    with blas_threads(args.threads), engine_or_exit(args.dask, log=print) as engine, \
            RunSteps(total, "validate (run-steps)", bars_wanted(args.quiet)) as bar:
        out = validate(plant, design, args.lags, args.amplitude, args.seed, engine, progress=bar)
    out["run_steps"] = total            # plant run-steps spent (`validation_run_steps`)
    for key, val in out.items():
        print(f"{key:28s} {val:.3e}" if isinstance(val, float) else f"{key:28s} {val}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    """The old `validate` command: `sep validate` with a deprecation line."""
    return legacy_main("validate", argv)


if __name__ == "__main__":
    sys.exit(main())
