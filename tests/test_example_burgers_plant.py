"""Physics tests of the worked example of a user's own plant: examples/burgers (sep_burgers).

The plant is imported whether or not the package is installed (examples/burgers goes on
sys.path if `import sep_burgers` fails). Fast: a few seconds in all.
"""
from __future__ import annotations

import ast
import json
import sys
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "burgers"
try:
    import sep_burgers  # noqa: F401
except ImportError:
    sys.path.insert(0, str(EXAMPLE))
from sep_burgers.plant import BurgersPlant, solve_periodic_tridiagonal  # noqa: E402

from sep_plant.conformance import check_plant  # noqa: E402
from sep_plant.plants import make_plant  # noqa: E402


@pytest.fixture(scope="module")
def plant() -> BurgersPlant:
    return BurgersPlant()


def semi_discrete_rhs(plant: BurgersPlant, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """dv_i/dt of the plant's spatial discretization, written independently of its step:
    -(v_{i+1}^2 - v_{i-1}^2) / (4h) + nu (v_{i+1} - 2 v_i + v_{i-1}) / h^2 + sum_j b_j(x_i) u_j
    (periodic; valid while the cell Peclet number |v| h / (4 nu) <= 1, checked by the callers)."""
    h, nu = plant.h, plant.viscosity
    vp, vm = np.roll(v, -1, axis=-1), np.roll(v, 1, axis=-1)
    return -(vp ** 2 - vm ** 2) / (4 * h) + nu * (vp - 2 * v + vm) / h ** 2 + u @ plant.actuator_profiles().T


def rk4_reference(plant: BurgersPlant, v0: np.ndarray, U: np.ndarray, substeps: int) -> np.ndarray:
    """Classical RK4 with `substeps` steps per plant step, inputs held over each plant step."""
    v, tau = v0.copy(), plant.dt / substeps
    for u in U:
        for _ in range(substeps):
            k1 = semi_discrete_rhs(plant, v, u)
            k2 = semi_discrete_rhs(plant, v + 0.5 * tau * k1, u)
            k3 = semi_discrete_rhs(plant, v + 0.5 * tau * k2, u)
            k4 = semi_discrete_rhs(plant, v + tau * k3, u)
            v = v + tau / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return v


def run(plant: BurgersPlant, v0: np.ndarray, U: np.ndarray) -> np.ndarray:
    v = v0
    for u in U:
        v = plant.step(v, u)
    return v


# ------------------------------------------------------------------ protocol
def test_conformance(plant):
    check_plant(plant)                                  # zero input
    check_plant(plant, np.full(plant.n_u, 0.3))         # a spin-up input
    check_plant(BurgersPlant(n_x=33, actuator_centers=[0.0, 0.5], sensor_positions=[0.1]), np.ones(2))


def test_description(plant):
    assert (plant.n_x, plant.n_u, plant.n_y, plant.n_field) == (128, 4, 3, 128)
    assert (plant.field_name, plant.field_unit) == ("velocity", "m/s")
    assert plant.field_is_state and plant.noise_on_inputs
    xyz = plant.field_coordinates()
    assert xyz.shape == (128, 3) and np.allclose(xyz[:, 1:], 0.0)
    assert xyz[0, 0] == 0.0 and xyz[-1, 0] == pytest.approx(1.0 - 1.0 / 128)
    assert list(plant.sensor_nodes()) == [26, 64, 102]


def test_config_is_json_and_rebuilds(plant):
    cfg = plant.config()
    text = json.dumps(cfg, sort_keys=True)
    assert all(not isinstance(v, tuple) for v in cfg.values())
    assert json.dumps(BurgersPlant(**json.loads(text)).config(), sort_keys=True) == text
    import inspect
    assert set(cfg) == set(inspect.signature(BurgersPlant).parameters)


@pytest.mark.parametrize("key, value, words", [
    ("n_x", 4, "n_x must be >= 8"),
    ("n_x", 12.5, "n_x must be an integer"),
    ("viscosity", 0.0, "viscosity must be > 0"),
    ("dt", -0.1, "dt must be > 0"),
    ("length", float("nan"), "length must be finite"),
    ("actuator_centers", [], "actuator_centers must be a non-empty list"),
    ("actuator_centers", [0.2, 1.0], "actuator_centers[1] must be < 1"),
    ("actuator_width", 0.001, "actuator_width must be >="),
    ("actuator_gain", "1", "actuator_gain must be a number"),
    ("sensor_positions", [0.5, 0.501], "sensor_positions: two sensors fall on the same grid node"),
    ("pulse_center", -0.1, "pulse_center must be >= 0"),
])
def test_bad_keys_name_the_key(key, value, words):
    with pytest.raises(ValueError) as exc:
        BurgersPlant(**{key: value})
    assert words in str(exc.value)


def test_found_by_type_string():
    p = make_plant("sep_burgers.plant:BurgersPlant", {"n_x": 64})
    assert isinstance(p, BurgersPlant) and p.n_x == 64


def test_found_by_entry_point_when_installed():
    from importlib.metadata import entry_points

    if "burgers" not in {ep.name for ep in entry_points(group="sep.plants")}:
        pytest.skip("sep-burgers is not installed (pip install --no-build-isolation --no-deps -e examples/burgers)")
    p = make_plant("burgers", {})
    assert type(p).__name__ == "BurgersPlant" and p.config() == BurgersPlant().config()


def test_plant_does_not_import_sep():
    """The protocol is structural: the example depends on numpy and scipy only."""
    for path in (EXAMPLE / "sep_burgers").glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else []
            assert not any(n.split(".")[0].startswith("sep_") and n.split(".")[0] != "sep_burgers"
                           for n in names), f"{path.name} imports {names}"


# ------------------------------------------------------------------ physics
def test_rest_stays_at_rest_and_uniform_flow_is_an_equilibrium(plant):
    zero = np.zeros((3, plant.n_x))
    assert np.array_equal(plant.step(zero, np.zeros(plant.n_u)), zero)
    uniform = np.full((2, plant.n_x), 0.7)
    assert np.allclose(plant.step(uniform, np.zeros(plant.n_u)), 0.7, rtol=0, atol=1e-13)


def test_step_matches_fine_rk4_reference_to_first_order(plant):
    """25 steps (1 s) of the steepening pulse, with a spin-up input, against RK4 at dt / 40 on the
    same semi-discrete equations (RK4 itself is converged to 1e-10 there): max error below 5 % of
    the field's maximum (3.5 %, 0.015 m/s, at the defaults), and first order in dt (halving dt
    halves the error)."""
    rng = np.random.default_rng(3)
    U = 0.3 + 0.1 * rng.standard_normal((25, plant.n_u))
    v0 = plant.initial_profile()
    assert np.max(np.abs(v0)) * plant.h / (4 * plant.viscosity) < 1        # central differences throughout
    ref = rk4_reference(plant, v0, U, substeps=40)
    err = np.max(np.abs(run(plant, v0[None], U)[0] - ref))
    assert err < 0.05 * np.max(np.abs(ref))
    half = BurgersPlant(**{**plant.config(), "dt": plant.dt / 2})
    err_half = np.max(np.abs(run(half, v0[None], np.repeat(U, 2, axis=0))[0] - ref))
    assert 1.7 < err / err_half < 2.3


def test_one_step_local_error_is_second_order(plant):
    v0 = plant.initial_profile()
    u = np.array([0.4, -0.2, 0.1, 0.3])
    errs = []
    for dt in (0.04, 0.02):
        p = BurgersPlant(**{**plant.config(), "dt": dt})
        errs.append(np.max(np.abs(p.step(v0[None], u)[0] - rk4_reference(p, v0, u[None], substeps=20))))
    assert errs[0] < 5e-3 and 3.5 < errs[0] / errs[1] < 4.5


def test_momentum_changes_only_through_the_actuators(plant):
    """On the ring, P = h sum_i v_i changes per step by exactly dt sum_j g_j (u_j + w_j),
    g_j = h sum_i b_j(x_i): the flux and viscous terms telescope (round-off only)."""
    rng = np.random.default_rng(7)
    g = plant.h * plant.actuator_profiles().sum(axis=0)
    assert np.allclose(g, plant.actuator_width * np.sqrt(2 * np.pi), rtol=1e-9)  # the Gaussians integrate to s sqrt(2 pi)
    X = plant.initial_state(4) + 0.2 * rng.standard_normal((4, plant.n_x))
    for _ in range(50):
        U = 0.5 * rng.standard_normal((4, plant.n_u))
        W = 0.15 * rng.standard_normal((4, plant.n_u))
        X1 = plant.step(X, U, W)
        dP = plant.h * (X1.sum(axis=1) - X.sum(axis=1))
        assert np.allclose(dP, plant.dt * (U + W) @ g, rtol=0, atol=1e-13)
        X = X1


def test_unforced_flow_relaxes_to_uniform_level(plant):
    """Without forcing the pulse spreads round the ring to the uniform level P / L."""
    v = run(plant, plant.initial_state(1), np.zeros((500, plant.n_u)))[0]    # 20 s
    level = plant.initial_profile().mean()
    assert np.max(np.abs(v - level)) < 0.01 * plant.pulse_amplitude


def test_nonnegative_stays_nonnegative_even_where_upwinding_takes_over():
    """The implicit matrix is an M-matrix (hybrid central/upwind): with no forcing a
    non-negative field stays non-negative, also for a 5 m/s pulse (cell Peclet number 2)."""
    p = BurgersPlant(pulse_amplitude=5.0, pulse_width=0.03)
    v = p.initial_state(1)
    assert np.max(v) * p.h / (4 * p.viscosity) > 1
    for _ in range(50):
        v = p.step(v, np.zeros(p.n_u))
        assert v.min() >= -1e-14 and np.all(np.isfinite(v))


def test_batch_equals_one_by_one(plant):
    rng = np.random.default_rng(11)
    X = plant.initial_state(6) + 0.3 * rng.standard_normal((6, plant.n_x))
    U = rng.standard_normal((6, plant.n_u))
    W = 0.2 * rng.standard_normal((6, plant.n_u))
    batch = plant.step(X, U, W)
    single = np.vstack([plant.step(X[i:i + 1], U[i], W[i]) for i in range(6)])
    assert np.allclose(batch, single, rtol=1e-12, atol=1e-14)
    assert np.allclose(plant.step(X, U + W), batch, rtol=1e-12, atol=1e-14)     # noise on the inputs


def test_nonlinearity_matters(plant):
    """From rest, pushing with +a and with -a does not give mirror images (advection by the
    flow itself), and the unforced pulse steepens: its steepest descent grows before viscosity
    wins, which a linear diffusion would never do."""
    rest = np.zeros((1, plant.n_x))
    U = np.tile([0.8, 0.0, 0.0, 0.0], (25, 1))                              # one actuator, 1 s
    up, down = run(plant, rest, U)[0], run(plant, rest, -U)[0]
    assert np.max(np.abs(up + down)) > 0.1 * np.max(np.abs(up - down))
    v = plant.initial_state(1)
    slopes = []
    for _ in range(25):
        slopes.append(np.max(np.roll(v[0], 1) - v[0]) / plant.h)            # steepest descent -v_x
        v = plant.step(v, np.zeros(plant.n_u))
    assert max(slopes) > 1.3 * slopes[0]


def test_periodic_solver_against_dense():
    rng = np.random.default_rng(5)
    M, n = 3, 9
    lower, upper = -rng.uniform(0.1, 1, (M, n)), -rng.uniform(0.1, 1, (M, n))
    diag = 1.0 + rng.uniform(2, 3, (M, n))
    rhs = rng.standard_normal((M, n))
    v = solve_periodic_tridiagonal(lower, diag, upper, rhs)
    for m in range(M):
        A = np.diag(diag[m]) + np.diag(upper[m, :-1], 1) + np.diag(lower[m, 1:], -1)
        A[0, -1], A[-1, 0] = lower[m, 0], upper[m, -1]
        assert np.allclose(A @ v[m], rhs[m], rtol=0, atol=1e-12)
