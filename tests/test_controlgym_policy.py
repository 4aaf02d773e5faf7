"""A small controlgym env through design -> policy -> the env's own reward, and the policy's
observation timing on the controller core (EstimatorCore.predicted)."""
from __future__ import annotations

import importlib.util

import numpy as np
import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("controlgym") is None,
                                reason="controlgym is not installed (make venv installs it: requirements-controlgym.txt)")

KEYS = dict(n_state=32, n_steps=20, process_noise_cov=1e-5, sensor_noise_cov=0.05)


@pytest.fixture(scope="module")
def design():
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_plant.plants.controlgym import ControlgymPlant, controlgym_problem

    plant = ControlgymPlant(env="burgers", noise_modes=4, mean_samples=100, **KEYS)
    problem = controlgym_problem(plant, target="0.1 * cos(2 * pi * x)")
    d = run_design(plant, problem, DesignSettings(n_r=6, p=4, q=4, ensemble=30, max_iter=4, belief_iter=1),
                   show_progress=False, log=lambda m: None)
    return plant, d


def _episodes(env, policy, seeds):
    out = []
    for s in seeds:
        obs, _ = env.reset(seed=s)
        if policy is not None:
            policy.reset()
        total = 0.0
        for _ in range(env.n_steps):
            obs, r, *_ = env.step(policy.act(obs) if policy is not None else np.zeros(env.n_action))
            total += r
        out.append(total)
    return np.array(out)


def test_design_runs_as_a_policy_on_the_env(design):
    """design -> DesignPolicy -> the env's reward: sep's nominal and LQG beat the zero input on
    the env's own noise and resets; the design accounted for the uncertain initial state."""
    from sep_control.control.policy import DesignPolicy
    from sep_plant.plants.controlgym import make_env

    plant, d = design
    assert d.meta["initial_prior"]["run_steps"] > 0 and d.meta["initial_prior"]["n_c"] >= 1
    env = make_env("burgers", **KEYS)
    env.set_target_state(d.problem.target_field(plant.field_coordinates()))
    seeds = range(5)
    zero = _episodes(env, None, seeds)
    lqg = _episodes(env, DesignPolicy(d, "rom_lqg", observation_lag=1), seeds)
    opened = _episodes(env, DesignPolicy(d, "open_loop", observation_lag=1), seeds)
    assert np.all(np.isfinite(lqg))
    assert lqg.mean() > zero.mean() and opened.mean() > zero.mean()


def test_lagged_policy_commands_from_the_predicted_estimate(design):
    """observation_lag=1: call k >= 2 updates step k-1, predicts with u_{k-1} and commands from
    zhat_{k|k-1}; the same numbers by hand on the filter and the law."""
    from sep_control.control.controllers import make_controller
    from sep_control.control.policy import DesignPolicy
    from sep_estimator.tvkf import KalmanFilter

    _, d = design
    rng = np.random.default_rng(3)
    ys = d.nominal.y[:6] + 0.05 * rng.standard_normal((6, d.nominal.y.shape[1]))
    pol = DesignPolicy(d, "rom_lqg", observation_lag=1)
    acts = [pol.act(ys[0]), pol.act(ys[0] + 1.0)] + [pol.act(ys[k - 1]) for k in range(2, 6)]
    law = make_controller("rom_lqg", d.lqg, d.problem, d.nominal.u)
    kf = KalmanFilter(d.lqg)
    a = kf.update(0, ys[0] - d.nominal.y[0])
    u = [law.command(0, a[0])]
    for k in range(1, 6):
        if k >= 2:
            kf.update(k - 1, ys[k - 1] - d.nominal.y[k - 1])
        kf.predict(k - 1, (u[-1] - d.nominal.u[k - 1])[None])
        u.append(law.command(k, kf.a[0]))
    np.testing.assert_allclose(np.array(acts), np.array(u), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="predicted"):
        pol.core.predicted(2)


def test_policy_refuses_bad_input(design):
    from sep_control.control.policy import DesignPolicy

    _, d = design
    with pytest.raises(ValueError, match="observation_lag"):
        DesignPolicy(d, observation_lag=2)
    pol = DesignPolicy(d)
    with pytest.raises(ValueError, match="outputs"):
        pol.act(np.zeros(3))


def test_mpc_policy_keeps_the_envs_action_limit(design):
    """rom_mpc as a policy on a design whose problem has the env's action limit: the actions stay
    inside it and the episode's reward is finite."""
    import dataclasses

    from sep_control.control.policy import DesignPolicy
    from sep_plant.plants.controlgym import make_env

    plant, d = design
    limited = dataclasses.replace(d, scenario=d.scenario.replace(u_min=-0.05, u_max=0.05))
    pol = DesignPolicy(limited, "rom_mpc", observation_lag=1, mpc={"horizon": 5})
    env = make_env("burgers", **KEYS)
    obs, _ = env.reset(seed=1)
    total = 0.0
    for _ in range(env.n_steps):
        u = pol.act(obs)
        assert np.all(np.abs(u) <= 0.05 + 1e-12)
        obs, r, *_ = env.step(u)
        total += r
    assert np.isfinite(total)
