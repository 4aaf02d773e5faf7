"""A user's own plant for sep: the viscous Burgers equation on a ring, with distributed actuators.

Model (a simple velocity/transport profile: flow round a closed annular channel of
circumference L; x in [0, L) along the centre line, x = L is x = 0 again)::

    v_t + v v_x = nu v_xx + sum_j b_j(x) (u_j + w_j),        v(x + L, t) = v(x, t)
    b_j(x)  = g exp(-d(x, c_j)^2 / (2 s^2))                  (d: distance round the ring)
    v(x, 0) = v_init + a_0 exp(-d(x, x_0)^2 / (2 s_0^2))     (known initial profile)
    y_m     = v(x at sensor m) (+ sensor noise, added by sep)

    v      velocity [m/s] (the state and the field, one value per node)
    nu     kinematic viscosity [m^2/s]               key `viscosity`
    u_j    actuator command: body force, i.e. acceleration at the actuator centre [m/s^2]
    w_j    process noise on the actuators (sep adds it: noise_on_inputs)
    g, s   actuator gain [-] and width [m]            keys `actuator_gain`, `actuator_width` (x L)
    c_j    actuator centres                          key `actuator_centers` (fractions of L)

Why a ring (periodic ends). The momentum P = integral of v dx changes only through the
actuators, dP/dt = sum_j (integral of b_j dx) (u_j + w_j): uniform flow at *any* speed is an
equilibrium, and the level of the flow is neutrally stable. Under actuator noise the level is a
random walk, so the open loop drifts away from a target speed however good the nominal: a
problem that needs feedback. Walls (v = 0 at both ends) would pin the flow near the ends
(no constant target could be held there) and damp every mode; an inflow/outflow channel
washes every disturbance out in one transit time (nothing to control). The ring also makes a
clean physics check: the scheme below conserves P exactly.

Discretization. Nodes x_i = i h, h = L / n_x, i = 0..n_x-1. Conservative central differences
for the flux F = v^2/2 and the viscous term, and one *linearly implicit* Euler step in which
the advecting velocity is frozen at the current state a = v_k (F_{k+1} ~ a v_{k+1} / 2)::

    v_{k+1,i} - v_{k,i} = - dt (a_{i+1} v_{k+1,i+1} - a_{i-1} v_{k+1,i-1}) / (4 h)
                          + dt (nu_{i+1/2} (v_{k+1,i+1} - v_{k+1,i}) - nu_{i-1/2} (v_{k+1,i} - v_{k+1,i-1})) / h^2
                          + dt sum_j b_j(x_i) (u_{k,j} + w_{k,j})

One periodic tridiagonal system per run; a batch of M runs is stacked block-diagonally and
solved in ONE LAPACK dgtsv call with two right-hand sides (the periodic corners are removed by
a Sherman-Morrison rank-one correction, `solve_periodic_tridiagonal`).

* Implicit, so the step is stable at any dt: at the default dt the flow crosses 2.6 cells per
  step (Courant number v dt / h = 2.6 at 0.5 m/s), where an explicit step would blow up.
* Central, not upwind, differences: the face viscosity is nu_{i+1/2} = max(nu, h max|a| / 4)
  (hybrid differencing). While the cell Peclet number |a| h / (4 nu) <= 1 -- |v| <= 2.56 m/s
  at the defaults, about five times any velocity of the control problem below -- this is plain
  central differencing: second order in space, no numerical viscosity. Beyond, it becomes
  first-order upwinding. Either way every off-diagonal is <= 0 and every column sums to 1, so
  the matrix is an M-matrix: the solve is well conditioned, a non-negative field stays
  non-negative (no undershoots at a steepening front), and P is conserved to round-off.
  Upwinding everywhere would add a numerical viscosity |v| h / 2 = 0.002 m^2/s at 0.5 m/s,
  40 % of nu.
* Time error: first order (the price of the M-matrix at Courant numbers above 1). At the
  defaults, after the first second -- the pulse steepening while the actuators push -- the
  field is within 0.015 m/s (3.5 % of its maximum) of a fine-step RK4 integration of the same
  semi-discrete equations; halving dt halves that (tests/test_example_burgers_plant.py).

Defaults and time scales (L = 1 m, n_x = 128, h = 7.8 mm, nu = 0.005 m^2/s, dt = 0.04 s):
    four actuators at 1/8, 3/8, 5/8, 7/8 L, width s = 0.04 L, gain 1 (each adds
    g s sqrt(2 pi) = 0.1 m x u_j to dP/dt); three sensors at 0.2, 0.5, 0.8 L; initial profile:
    fluid at rest with a velocity pulse a_0 = 0.5 m/s, s_0 = 0.1 L at x_0 = L/2 (P = 0.125 m^2/s).
    - transit time round the ring at 0.5 m/s: L / v = 2 s; Reynolds number v L / nu = 100;
    - viscous decay time of the k-th ring mode: L^2 / (4 pi^2 k^2 nu) = 5.1 s / k^2; of an
      actuator-sized bump: s^2 / nu = 0.3 s;
    - steepening: the pulse (Reynolds number a_0 s_0 / nu = 10) would break after
      s_0 sqrt(e) / a_0 = 0.33 s without viscosity; with it, its front steepens by 45 % over
      0.5 s into a viscous shock (width ~ 4 nu / a_0 = 4 cm, 5 nodes) that travels at the mean
      of the speeds on its two sides, and the pulse leans forward. Unforced, the pulse spreads
      round the ring to the uniform level P / L = 0.125 m/s (within 3 % of a_0 after 10 s).
Suggested control problem (problem keys of a sep scenario, not keys of this plant; see
`scenario.yaml` beside this package): spin the fluid up from the pulse to a uniform flow,
target 0.5 m/s within +-0.05 m/s over the last 40 % of N = 250 steps (t = 6..10 s), actuator
noise w_std = 0.15 m/s^2, sensor noise v_std = 0.02 m/s. The spin-up is strongly nonlinear:
the advection speed goes from 0 to 0.5 m/s, so the linearization changes from pure diffusion
to transport over the horizon. Afterwards the level random-walks (std ~0.02 m/s after 10 s)
and the open loop leaves the band in more than half the runs, while sep's ROM-LQG (three
sensors) keeps nearly all of them inside (1000 runs: 44.9 % and 99.8 % in band).

This module imports numpy and scipy only: a plant is anything with the attributes and methods
of sep's plant protocol (sep_plant.protocol); nothing is subclassed or imported from sep.
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np
from scipy.linalg import lapack

__all__ = ["BurgersPlant", "solve_periodic_tridiagonal"]


# ------------------------------------------------------------------ key checks
def _number(name: str, value: Any, *, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False, hi_open: bool = False) -> float:
    """A finite number in [lo, hi] (open ends with lo_open / hi_open); ValueError names the key."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise ValueError(f"{name} must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and (v >= hi if hi_open else v > hi):
        raise ValueError(f"{name} must be {'<' if hi_open else '<='} {hi:g}, got {v:g}")
    return v


def _integer(name: str, value: Any, *, lo: int) -> int:
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if int(value) < lo:
        raise ValueError(f"{name} must be >= {lo}, got {value}")
    return int(value)


def _fractions(name: str, value: Any) -> tuple[float, ...]:
    """A non-empty list of positions along the ring as fractions of L, each in [0, 1)."""
    if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple, np.ndarray)) or len(value) == 0:
        raise ValueError(f"{name} must be a non-empty list of positions in [0, 1) (fractions of L), "
                         f"got {value!r}")
    return tuple(_number(f"{name}[{i}]", p, lo=0.0, hi=1.0, hi_open=True) for i, p in enumerate(value))


# ------------------------------------------------------------------ linear algebra
def solve_periodic_tridiagonal(lower: np.ndarray, diag: np.ndarray, upper: np.ndarray,
                               rhs: np.ndarray) -> np.ndarray:
    """Solve, for every run m (row of the (M, n) arrays), the periodic tridiagonal system

        lower[m, i] v[m, i-1] + diag[m, i] v[m, i] + upper[m, i] v[m, i+1] = rhs[m, i]   (i mod n)

    with ONE LAPACK dgtsv call. The periodic corners A[0, n-1] = lower[:, 0] and
    A[n-1, 0] = upper[:, -1] are split off as a rank-one term, A = T + p q^T with
    p = (gamma, 0, .., 0, A[n-1, 0]), q = (1, 0, .., 0, A[0, n-1] / gamma), gamma = -A[0, 0]
    (Sherman-Morrison). The tridiagonal T of every run is stacked block-diagonally (zero
    coupling between runs) and solved for the two right-hand sides [rhs, p] at once:
    v = y - (q.y / (1 + q.z)) z with T y = rhs, T z = p.
    """
    M, n = diag.shape
    top_right = lower[:, 0]
    bottom_left = upper[:, -1]
    gamma = -diag[:, 0]
    d = diag.copy()
    d[:, 0] -= gamma
    d[:, -1] -= bottom_left * top_right / gamma
    sub = lower.copy()
    sub[:, 0] = 0.0                     # no coupling between the last node of run m-1 and run m
    sup = upper.copy()
    sup[:, -1] = 0.0
    p = np.zeros((M, n))
    p[:, 0] = gamma
    p[:, -1] = bottom_left
    b = np.stack([rhs.ravel(), p.ravel()], axis=1)
    _, _, _, sol, info = lapack.dgtsv(sub.ravel()[1:], d.ravel(), sup.ravel()[:-1], b,
                                      overwrite_dl=1, overwrite_d=1, overwrite_du=1, overwrite_b=1)
    if info != 0:
        raise FloatingPointError(f"tridiagonal solve failed (LAPACK info {info}): non-finite state or input?")
    y = sol[:, 0].reshape(M, n)
    z = sol[:, 1].reshape(M, n)
    ratio = top_right / gamma
    factor = (y[:, 0] + ratio * y[:, -1]) / (1.0 + z[:, 0] + ratio * z[:, -1])
    return y - factor[:, None] * z


def _ring_distance(x: np.ndarray, c: np.ndarray | float, length: float) -> np.ndarray:
    """Shortest distance between positions x and c round a ring of circumference `length`."""
    d = np.abs(np.asarray(x) - c) % length
    return np.minimum(d, length - d)


# ------------------------------------------------------------------ the plant
class BurgersPlant:
    """Viscous Burgers equation on a ring with Gaussian actuators and point sensors.

    Meets sep's plant protocol structurally (see the module docstring for the equations, the
    scheme and the defaults). Every constructor argument is a key of the scenario's `plant:`
    section; `config()` returns them all, so `BurgersPlant(**plant.config())` rebuilds it.
    """

    field_name = "velocity"
    field_unit = "m/s"
    field_is_state = True          # field(x) is the state itself
    noise_on_inputs = True         # step(x, u, w) == step(x, u + w)

    def __init__(self, n_x: int = 128, length: float = 1.0, viscosity: float = 0.005, dt: float = 0.04,
                 actuator_centers: Sequence[float] = (0.125, 0.375, 0.625, 0.875),
                 actuator_width: float = 0.04, actuator_gain: float = 1.0,
                 sensor_positions: Sequence[float] = (0.2, 0.5, 0.8),
                 v_init: float = 0.0, pulse_amplitude: float = 0.5, pulse_center: float = 0.5,
                 pulse_width: float = 0.1):
        self.n_x = _integer("n_x", n_x, lo=8)
        self.length = _number("length", length, lo=0.0, lo_open=True)
        self.viscosity = _number("viscosity", viscosity, lo=0.0, lo_open=True)
        self.dt = _number("dt", dt, lo=0.0, lo_open=True)
        self.actuator_centers = _fractions("actuator_centers", actuator_centers)
        self.actuator_width = _number("actuator_width", actuator_width, lo=1.0 / self.n_x, hi=0.5)
        self.actuator_gain = _number("actuator_gain", actuator_gain, lo=0.0, lo_open=True)
        self.sensor_positions = _fractions("sensor_positions", sensor_positions)
        self.v_init = _number("v_init", v_init)
        self.pulse_amplitude = _number("pulse_amplitude", pulse_amplitude)
        self.pulse_center = _number("pulse_center", pulse_center, lo=0.0, hi=1.0, hi_open=True)
        self.pulse_width = _number("pulse_width", pulse_width, lo=1.0 / self.n_x, hi=0.5)

        self.h = self.length / self.n_x
        self._x = np.arange(self.n_x) * self.h
        self._sensors = np.array([round(p * self.n_x) % self.n_x for p in self.sensor_positions])
        if len(set(self._sensors.tolist())) != len(self._sensors):
            raise ValueError("sensor_positions: two sensors fall on the same grid node; move them apart "
                             "or raise n_x")
        self._b_dt = self.dt * self.actuator_profiles()            # dt b_j(x_i), (n_x, n_u)

        self.n_u = len(self.actuator_centers)
        self.n_y = len(self.sensor_positions)
        self.n_field = self.n_x
        self.input_names = tuple(f"actuator_{j}" for j in range(self.n_u))
        self.output_names = tuple(f"sensor_{m}" for m in range(self.n_y))

    # ------------------------------------------------------------- description
    def config(self) -> dict[str, Any]:
        """The constructor's keys as JSON data (lists, not tuples)."""
        return {"n_x": self.n_x, "length": self.length, "viscosity": self.viscosity, "dt": self.dt,
                "actuator_centers": list(self.actuator_centers), "actuator_width": self.actuator_width,
                "actuator_gain": self.actuator_gain, "sensor_positions": list(self.sensor_positions),
                "v_init": self.v_init, "pulse_amplitude": self.pulse_amplitude,
                "pulse_center": self.pulse_center, "pulse_width": self.pulse_width}

    def grid(self) -> np.ndarray:
        """Node positions x_i = i h [m] along the ring, (n_x,)."""
        return self._x.copy()

    def field_coordinates(self) -> np.ndarray:
        """(n_x, 3) node positions in metres: the ring unrolled along x (y = z = 0)."""
        xyz = np.zeros((self.n_x, 3))
        xyz[:, 0] = self._x
        return xyz

    def sensor_nodes(self) -> np.ndarray:
        """Index of the node nearest each sensor position."""
        return self._sensors.copy()

    def actuator_profiles(self) -> np.ndarray:
        """b_j(x_i) = g exp(-d(x_i, c_j)^2 / (2 s^2)), shape (n_x, n_u)."""
        c = np.asarray(self.actuator_centers) * self.length
        d = _ring_distance(self._x[:, None], c[None, :], self.length)
        s = self.actuator_width * self.length
        return self.actuator_gain * np.exp(-0.5 * (d / s) ** 2)

    def initial_profile(self) -> np.ndarray:
        """v(x_i, 0) = v_init + a_0 exp(-d(x_i, x_0)^2 / (2 s_0^2)), (n_x,)."""
        d = _ring_distance(self._x, self.pulse_center * self.length, self.length)
        s0 = self.pulse_width * self.length
        return self.v_init + self.pulse_amplitude * np.exp(-0.5 * (d / s0) ** 2)

    # -------------------------------------------------------------------- API
    def initial_state(self, batch: int = 1) -> np.ndarray:
        """The known initial profile for every run: (batch, n_x)."""
        return np.tile(self.initial_profile(), (batch, 1))

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """v_{k+1} = f(v_k, u_k + w_k) for every run: (M, n_x), a new array (x is not modified)."""
        single = np.ndim(x) == 1
        V = np.atleast_2d(np.asarray(x, dtype=float))
        U = np.atleast_2d(np.asarray(u, dtype=float))
        if w is not None:
            U = U + np.atleast_2d(np.asarray(w, dtype=float))
        M, n = V.shape
        if n != self.n_x or U.shape[-1] != self.n_u or U.shape[0] not in (1, M):
            raise ValueError(f"step: expected states (M, {self.n_x}) and inputs (M, {self.n_u}) or "
                             f"({self.n_u},), got {V.shape} and {U.shape}")
        lower, diag, upper = self._implicit_matrix(V)
        rhs = V + U @ self._b_dt.T                      # v_k + dt sum_j b_j (u_j + w_j)
        out = solve_periodic_tridiagonal(lower, diag, upper, rhs)
        return out[0] if single else out

    def observe(self, x: np.ndarray) -> np.ndarray:
        """Noise-free sensor outputs: the velocity at the sensor nodes, (M, n_y)."""
        return np.asarray(x)[..., self._sensors]

    def field(self, x: np.ndarray) -> np.ndarray:
        """The velocity field is the state."""
        return x

    # --------------------------------------------------------------- scheme
    def face_viscosity(self, a: np.ndarray) -> np.ndarray:
        """nu_{i+1/2} = max(nu, h max(|a_i|, |a_{i+1}|) / 4): nu itself wherever the cell Peclet
        number is <= 1 (central differences), upwind-equivalent beyond. (M, n_x)."""
        a_abs = np.abs(a)
        return np.maximum(self.viscosity, 0.25 * self.h * np.maximum(a_abs, np.roll(a_abs, -1, axis=-1)))

    def _implicit_matrix(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row i of I + dt (advection frozen at a - viscous term): coefficients of v_{i-1},
        v_i, v_{i+1} (periodic), each (M, n_x)."""
        c_adv = self.dt / (4.0 * self.h)
        c_visc = self.dt / self.h ** 2
        nu_plus = self.face_viscosity(a)                 # nu_{i+1/2}
        nu_minus = np.roll(nu_plus, 1, axis=-1)          # nu_{i-1/2}
        upper = c_adv * np.roll(a, -1, axis=-1) - c_visc * nu_plus      # a_{i+1}
        lower = -c_adv * np.roll(a, 1, axis=-1) - c_visc * nu_minus     # a_{i-1}
        diag = 1.0 + c_visc * (nu_plus + nu_minus)
        return lower, diag, upper
