"""A design's ROM against fresh experiments on the nonlinear simulator (`sep validate`).

Two checks, relative errors as Frobenius norms over all steps:

    markov      the ROM's Markov parameters C_k A_{k-1}..A_{j+1} B_j against long central-difference
                impulse experiments (lags 1..L, beyond the p + q used to identify);
    prediction  the ROM's output and field response to a small random input sequence dU,
                dy_k = C_k a_k, df_k = G_k a_k with a_{k+1} = A_k a_k + B_k dU_k, a_0 = 0, against
                the simulator's y(U + dU) - y(U), f(U + dU) - f(U) (noise-free).

Pure numpy: no ROS import.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from sep_plant.protocol import Plant, fields, noise_channels, nominal_states, outputs

from sep_control.compute.progress import RunSteps
from sep_control.design.noise_sketch import SKETCH_FROM
from sep_control.design.tvera import SCHEMES, impulse_experiments


def validated_noise_channels(plant: Plant) -> int:
    """The noise channels `validate`'s experiments step beside the inputs: those of a plant whose
    noise is not on the inputs, none above SKETCH_FROM (the check compares the inputs' Markov
    parameters only; many channels would multiply its experiments for nothing)."""
    n_w = 0 if getattr(plant, "noise_on_inputs", True) else noise_channels(plant)
    return 0 if n_w > SKETCH_FROM else n_w


def impulse_run_steps(plant: Plant, n_steps: int, lags: int, scheme: str = "central", n_w: int | None = None) -> int:
    """Run-steps of `impulse_experiments` over N start steps with `lags` lags, with the nominal
    rollout over N + lags steps: central 2 N n_ch runs, forward N (n_ch + 1), of `lags` steps each
    (n_ch: the inputs and n_w noise channels, None: `validated_noise_channels`)."""
    n_ch = int(plant.n_u) + (validated_noise_channels(plant) if n_w is None else int(n_w))
    runs = n_steps * (2 * n_ch if SCHEMES[scheme] == 2 else n_ch + 1)
    return runs * lags + n_steps + lags


def validation_run_steps(plant: Plant, n_steps: int, lags: int) -> int:
    """Run-steps of `validate`: the impulse experiments and two nominal rollouts of N steps."""
    return impulse_run_steps(plant, n_steps, lags) + 2 * n_steps


def validate(plant: Plant, design, lags: int = 60, amplitude: float = 0.01, seed: int = 0, engine=None,
             progress=None) -> dict[str, Any]:
    """Markov and prediction errors of the design's ROM on `plant`.

    Parameters
    ----------
    plant : Plant
        The nonlinear plant (the design's, rebuilt from its scenario).
    design : Design
        The design whose ROM (A_k, B_k, C_k, G_k) and nominal input U are checked.
    lags : int
        Impulse-response length L of the Markov check.
    amplitude : float
        Std of the random input deviation dU, relative to the RMS nominal input.
    seed : int
        Seed of dU.
    engine : engine, optional
        Where the long impulse experiments run (`sep_control.compute.engine`); their chunks
        (4, or twice the workers) do not change the output Markov parameters.
    progress : RunSteps, optional
        Advanced by the run-steps done (`validation_run_steps` in all).

    Returns
    -------
    dict
        markov_rel_error, markov_lags, output_prediction_rel_error, field_prediction_rel_error,
        input_deviation_std (the std of dU) and n_r (the ROM's largest order).
    """
    U, N, rom = design.nominal.u, design.n_steps, design.rom
    progress = progress or RunSteps(0, "", enabled=False)
    rms_u = max(float(np.sqrt(np.mean(U**2))), 1e-3)
    delta = float(design.meta.get("validation", {}).get("impulse_amplitude", 0.01 * rms_u))

    chunks = 4 if engine is None else max(4, 2 * engine.workers)
    data = impulse_experiments(plant, U, lags, 0, delta, chunks=chunks, engine=engine,
                               inputs_only=validated_noise_channels(plant) == 0)
    progress.add(impulse_run_steps(plant, N, lags))
    Yr, Ye = rom.markov_all(lags), data.Y_inputs
    valid = (np.arange(N)[:, None] + np.arange(1, lags + 1)[None, :]) <= N
    markov = float(np.linalg.norm((Yr - Ye)[valid]) / np.linalg.norm(Ye[valid]))

    dU = np.random.default_rng(seed).standard_normal(U.shape) * amplitude * rms_u
    X_nom, X_pert = nominal_states(plant, U), nominal_states(plant, U + dU)
    progress.add(2 * N)
    dy_rom, df_rom = rom_response(rom, dU, design.info.n_y, design.info.n_field)
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


def rom_response(rom, dU: np.ndarray, n_y: int, n_field: int) -> tuple[np.ndarray, np.ndarray]:
    """The ROM's output and field deviations (N+1, n_y), (N+1, n_field) for the input deviation
    dU (N, n_u) from a_0 = 0: dy_k = C_k a_k, df_k = G_k a_k, a_{k+1} = A_k a_k + B_k dU_k."""
    N = dU.shape[0]
    a = np.zeros((1, rom.n))
    dy, df = np.zeros((N + 1, n_y)), np.zeros((N + 1, n_field))
    for k in range(N + 1):          # a recursion over steps: one state, nothing to batch
        dy[k] = a[0] @ rom.C[k].T
        df[k] = rom.G.apply(k, a)[0]
        if k < N:
            a = a @ rom.A[k].T + dU[k] @ rom.B[k].T
    return dy, df

