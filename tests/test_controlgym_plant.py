"""controlgym's PDE envs as sep plants: the fast path equals env.step, the plant conforms, and
initial states come from the env's own reset."""
from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("controlgym") is None,
                                reason="controlgym is not installed (make venv installs it: requirements-controlgym.txt)")


def _plant(**keys):
    from sep_plant.plants import make_plant

    return make_plant("controlgym", {"mean_samples": 20, **keys})


@pytest.mark.parametrize("env", ["allen_cahn", "burgers", "cahn_hilliard", "convection_diffusion_reaction",
                                 "fisher", "ginzburg_landau", "korteweg_de_vries", "kuramoto_sivashinsky",
                                 "schrodinger", "wave"])
def test_fast_path_equals_env_step(env):
    """FastStep (batched, the env's operators) == env.step with the noise off, to 1e-10, on random
    states around the env's own initial states and random inputs."""
    p = _plant(env=env)
    assert p._fast is not None
    rng = np.random.default_rng(7)
    X0 = p.initial_states(np.arange(4))
    X = X0 + 0.1 * rng.standard_normal(X0.shape)
    U = rng.standard_normal((4, p.n_u))
    fast = p.step(X, U)
    for m in range(4):
        p.env.reset(state=X[m].copy())
        ref = p.env.step(U[m].copy())[4]["state"]
        np.testing.assert_allclose(fast[m], ref, rtol=0, atol=1e-10)
        np.testing.assert_allclose(p.observe(X[m:m + 1])[0], p.env.reset(state=X[m].copy())[0], rtol=0, atol=1e-12)


def test_plant_conforms_and_rebuilds():
    from sep_plant.conformance import check_plant
    from sep_plant.plants import make_plant

    p = _plant(env="burgers", n_state=32, process_noise_cov=1e-5, sensor_noise_cov=0.05, noise_modes=6)
    check_plant(p)
    q = make_plant("controlgym", p.config())
    assert q.config() == p.config()
    assert (p.n_x, p.n_u, p.n_y, p.n_w) == (32, 8, 10, 6)
    slow = _plant(env="burgers", n_state=32, fast=False)
    check_plant(slow)
    x = p.initial_states([3, 4])
    np.testing.assert_allclose(slow.step(x, np.ones(8)), p.step(x, np.ones(8)), rtol=0, atol=1e-12)


def test_noise_is_off_in_the_plant_and_its_levels_go_to_the_problem():
    from sep_plant.plants.controlgym import controlgym_problem

    p = _plant(env="burgers", n_state=32, process_noise_cov=1e-4, sensor_noise_cov=0.04)
    assert p.env.process_noise_cov == 0 and p.env.sensor_noise_cov == 0
    pr = controlgym_problem(p)
    assert pr.w_std == pytest.approx(0.01) and pr.v_std == pytest.approx(0.2)
    assert pr.n_steps == p.env.n_steps and pr.r_u == pytest.approx(1.0 / 32)


def test_initial_states_are_the_envs_seeded_resets():
    from sep_plant.plants.controlgym import make_env

    p = _plant(env="burgers", n_state=32)
    env = make_env("burgers", n_state=32)
    X = p.initial_states([11, 12])
    for m, s in enumerate((11, 12)):
        np.testing.assert_array_equal(X[m], env.reset(seed=s)[1]["state"])
    assert not np.allclose(X[0], X[1])
    np.testing.assert_allclose(p.initial_state(2), np.tile(p.initial_states(np.arange(20)).mean(0), (2, 1)))


def test_controlgym_is_loaded_without_torch():
    from sep_plant.plants.controlgym import envs_module

    envs_module()
    assert "torch" not in sys.modules


def test_unknown_env_is_refused():
    from sep_plant.plants import make_plant
    from sep_plant.plants.keys import PlantConfigError

    with pytest.raises(PlantConfigError, match="env must be one of"):
        make_plant("controlgym", {"env": "pendulum"})


def test_a_generic_gym_env_is_a_plant():
    """plant type gym: any resettable env by its factory, with the noise keys switched off."""
    from sep_plant.conformance import check_plant
    from sep_plant.plants import make_plant

    p = make_plant("gym", {"env": "sep_plant.plants.controlgym:make_env",
                           "env_kwargs": {"env": "burgers", "n_state": 16, "sensor_noise_cov": 0.1},
                           "noise_off": {"process_noise_cov": 0.0, "sensor_noise_cov": 0.0},
                           "mean_samples": 5, "noise_modes": 4})
    check_plant(p)
    assert (p.n_x, p.n_u, p.n_y, p.n_w, p.dt) == (16, 8, 10, 4, 0.05)
    fast = _plant(env="burgers", n_state=16)
    x = fast.initial_states([1, 2])
    np.testing.assert_allclose(p.step(x, np.ones(8)), fast.step(x, np.ones(8)), rtol=0, atol=1e-12)
