"""`validate`: check a design's ROM against fresh experiments on the nonlinear simulator."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from sep_plant.protocol import Plant, fields, nominal_states, outputs

from sep_control.cli.common import (Formatter, add_dask, add_device, add_threads, blas_threads, design_or_exit,
                         engine_or_exit, fail, plant_or_exit)
from sep_control.design.tvera import impulse_experiments

DESCRIPTION = """\
Validate the reduced-order model of a design file against the nonlinear plant (rebuilt from
the design file's scenario):
  markov     ROM Markov parameters C_k A_{k-1}..A_{j+1} B_j vs long central-difference
             impulse experiments (lags up to --lags, beyond the p+q used to identify);
  prediction ROM output and field prediction vs the nonlinear simulator for a random
             small input sequence du (noise-free), relative to the deviation itself.
Relative errors are Frobenius norms over all steps.

Example:  validate --design out/design.npz --json out/validate.json
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="validate", description=DESCRIPTION, formatter_class=Formatter)
    p.add_argument("--design", metavar="DESIGN_FILE", required=True)
    p.add_argument("--lags", type=int, default=60, help="impulse-response length for the Markov check")
    p.add_argument("--amplitude", type=float, default=0.01,
                   help="random input deviation std, relative to the RMS nominal input")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="PATH")
    add_threads(p)
    add_dask(p)
    add_device(p)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.lags < 1 or not args.amplitude > 0:
        fail("--lags must be >= 1 and --amplitude > 0")
    design = design_or_exit(args.design)
    plant = plant_or_exit(design.scenario, f"{args.design} (its scenario)", device=args.device)
    with blas_threads(args.threads), engine_or_exit(args.dask, log=print) as engine:
        out = validate(plant, design, args.lags, args.amplitude, args.seed, engine)
    for key, val in out.items():
        print(f"{key:28s} {val:.3e}" if isinstance(val, float) else f"{key:28s} {val}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


def validate(plant: Plant, design, lags: int = 60, amplitude: float = 0.01, seed: int = 0, engine=None) -> dict:
    """Markov and prediction errors of the design's ROM. The long impulse experiments run in
    chunks on `engine` (their output Markov parameters do not depend on the chunks)."""
    U = design.nominal.u
    N = design.n_steps
    rom = design.rom
    rms_u = max(float(np.sqrt(np.mean(U**2))), 1e-3)
    delta = float(design.meta.get("validation", {}).get("impulse_amplitude", 0.01 * rms_u))

    # Markov parameters (input channels) vs long impulse experiments
    chunks = 4 if engine is None else max(4, 2 * engine.workers)
    data = impulse_experiments(plant, U, lags, 1, delta, chunks=chunks, engine=engine)
    Yr = rom.markov_all(lags)
    Ye = data.Y_inputs
    valid = (np.arange(N)[:, None] + np.arange(1, lags + 1)[None, :]) <= N
    markov = float(np.linalg.norm((Yr - Ye)[valid]) / np.linalg.norm(Ye[valid]))

    # output and field prediction for a random small input sequence
    rng = np.random.default_rng(seed)
    dU = rng.standard_normal(U.shape) * amplitude * rms_u
    X_nom = nominal_states(plant, U)
    X_pert = nominal_states(plant, U + dU)
    a = np.zeros((1, rom.n))
    dy_rom = np.zeros((N + 1, design.info.n_y))
    df_rom = np.zeros((N + 1, design.info.n_field))
    for k in range(N + 1):
        dy_rom[k] = a[0] @ rom.C[k].T
        df_rom[k] = rom.G.apply(k, a)[0]
        if k < N:
            a = a @ rom.A[k].T + dU[k] @ rom.B[k].T
    dy_sim = outputs(plant, X_pert) - outputs(plant, X_nom)
    df_sim = fields(plant, X_pert) - fields(plant, X_nom)
    return {
        "markov_rel_error": markov,
        "markov_lags": lags,
        "output_prediction_rel_error": float(np.linalg.norm(dy_rom - dy_sim) / np.linalg.norm(dy_sim)),
        "field_prediction_rel_error": float(np.linalg.norm(df_rom - df_sim) / np.linalg.norm(df_sim)),
        "input_deviation_std": float(amplitude * rms_u),
        "n_r": int(rom.dims.max()),
    }


if __name__ == "__main__":
    sys.exit(main())
