"""Many process-noise channels are identified on a few random combinations (`noise_sketch`)."""
from __future__ import annotations

import numpy as np
import pytest

from rd_plant import ReactionDiffusionPlant
from sep_control.design.impulse import impulse_experiments
from sep_control.design.noise_sketch import SKETCH_FROM, SKETCH_PROBES, NoiseSketch, sketch_for, trace_std_error
from sep_control.design.pipeline import DesignSettings, run_design
from sep_control.design.tvera import identify, markov_relative_error
from sep_plant.problem import Problem


def test_sketch_starts_above_the_threshold_and_skips_silent_channels():
    assert sketch_for(SKETCH_FROM, 1.0) is None
    sk = sketch_for(SKETCH_FROM + 1, 0.5)
    assert sk is not None and (sk.n_w, sk.rank) == (SKETCH_FROM + 1, SKETCH_PROBES)
    assert sketch_for(200, 1.0, probes=0) is None
    std = np.zeros(200)
    std[:SKETCH_PROBES] = 1.0                      # no more channels with noise than probes
    assert sketch_for(200, std) is None


def test_lifted_noise_input_gives_the_noise_covariance_without_bias():
    rng = np.random.default_rng(3)
    n_r, n_w, J = 4, 90, 3000
    std = rng.uniform(0.5, 2.0, n_w)
    std[:5] = 0.0                                  # silent channels get no probe and no column
    sk = NoiseSketch(tuple(std), 16)
    Bw = rng.standard_normal((n_r, n_w)) * np.linspace(1.0, 0.1, n_w)
    Bs = np.stack([Bw @ sk.directions(j) for j in range(J)])        # what the experiments see
    lifted = sk.lift(Bs)
    assert lifted.shape == (J, n_r, n_w) and not np.any(lifted[:, :, :5])
    np.testing.assert_allclose(sk.sketched(lifted), Bs, atol=1e-12)  # back on the probes exactly
    W = np.diag(std**2)
    Q = Bw @ W @ Bw.T
    Qhat = np.mean(lifted @ W @ lifted.transpose(0, 2, 1), axis=0)
    assert np.linalg.norm(Qhat - Q) / np.linalg.norm(Q) < 0.05    # sampling error ~ 1/sqrt(J r_w)
    one = lifted[0] @ W @ lifted[0].T
    err = trace_std_error(Bs[:1], sk)
    assert 0.0 < err < 1.0 and abs(np.trace(one) / np.trace(Q) - 1) < 4 * err + 0.1


def _problem(N: int) -> Problem:
    return Problem(n_steps=N, target=0.3, band=0.05, w_std=0.003, v_std=0.02, u_init=0.2, r_u=0.01)


def test_identification_of_every_node_uses_the_sketch_and_keeps_the_plant_channels():
    plant = ReactionDiffusionPlant(n_x=81)                       # n_w = 81 > SKETCH_FROM
    U = np.full((30, plant.n_u), 0.2)
    ident = identify(plant, U, 5, 5, 10, noise_std=0.003)
    assert ident.data.noise is not None and ident.data.Y.shape[-1] == plant.n_u + SKETCH_PROBES
    assert ident.model.Bw.shape == (30, 10, 81)
    assert markov_relative_error(ident.model, ident.data.Y, ident.data.noise) < 0.2
    # the combinations belong to the start step, whatever chunk runs it
    chunked = identify(plant, U, 5, 5, 10, noise_std=0.003, chunks=3)
    np.testing.assert_array_equal(chunked.data.Y, ident.data.Y)
    few = identify(ReactionDiffusionPlant(n_x=81, noise_modes=SKETCH_FROM), U, 5, 5, 10)
    assert few.data.noise is None and few.data.Y.shape[-1] == plant.n_u + SKETCH_FROM   # at the threshold: exact


def test_design_with_noise_on_every_node_costs_the_order_of_a_few_channels():
    N, st = 40, DesignSettings(p=6, q=6, n_r=10, max_iter=3, belief=False)
    designs, logs = {}, {}
    for name, modes in (("modes", 8), ("every", None)):
        plant = ReactionDiffusionPlant(n_x=201, noise_modes=modes, diffusion=0.002)
        lines: list[str] = []
        designs[name] = run_design(plant, _problem(N), st, show_progress=False, log=lines.append)
        logs[name] = lines
    steps = {k: d.meta["run_steps"]["total"] for k, d in designs.items()}
    # 201 channels one by one would be 2 N 204 (p + q) run-steps per identification (25x the
    # 8 modes'); sketched they are 2 N (3 + SKETCH_PROBES)
    assert steps["every"] < 5 * steps["modes"]
    assert designs["every"].lqg.rom.Bw.shape[2] == 201
    line = next(m for m in logs["every"] if "random combinations" in m)
    assert f"{6 * 5} x {6 * (3 + SKETCH_PROBES)} instead of {6 * 5} x {6 * 204}" in line
    assert not any("random combinations" in m for m in logs["modes"])


def test_validation_of_a_many_channel_design_steps_the_inputs_only():
    from sep_control.design.runsteps import RunStepMeter, metered
    from sep_control.evaluation.validation import validate, validation_run_steps

    plant = ReactionDiffusionPlant(n_x=81, diffusion=0.002)
    N, lags = 30, 12
    d = run_design(plant, _problem(N), DesignSettings(p=5, q=5, n_r=8, max_iter=2, belief=False),
                   show_progress=False, log=lambda m: None)
    meter = RunStepMeter()
    out = validate(metered(plant, meter), d, lags=lags)
    # central impulses on the 3 inputs only (the check compares the inputs' Markov parameters),
    # the nominal over N + lags steps, two rollouts of N steps
    assert meter.total == validation_run_steps(plant, N, lags) == 2 * N * 3 * lags + N + lags + 2 * N
    assert np.isfinite(out["markov_rel_error"])


def test_strided_impulses_hold_a_sketch_over_the_stride():
    # a linear, time-invariant plant: every start step's responses are the same, so strided
    # impulses must give what impulses at every start step give, noise columns included; a
    # linear interpolation of the sketch's columns would mix two start steps' combinations
    plant = ReactionDiffusionPlant(n_x=81, a=0.0, b=0.0)              # n_w = 81 > SKETCH_FROM
    U = np.full((12, plant.n_u), 0.2)
    held = sketch_for(plant.n_w, 0.003, hold=2)
    assert held.directions(5).tolist() == held.directions(4).tolist() != held.directions(6).tolist()
    every = impulse_experiments(plant, U, 6, 3, 1e-2, scheme="forward", noise=held)
    strided = impulse_experiments(plant, U, 6, 3, 1e-2, scheme="forward", noise=held, stride=2)
    np.testing.assert_allclose(strided.Y, every.Y, rtol=0, atol=1e-9 * np.abs(every.Y).max())
    with pytest.raises(ValueError, match="held over the stride"):
        impulse_experiments(plant, U, 6, 3, 1e-2, noise=sketch_for(plant.n_w, 0.003), stride=2)
    # and an identification with strided impulses holds its sketch itself
    assert identify(plant, U, 3, 3, 10, noise_std=0.003, stride=2).data.noise.hold == 2
