"""Scenario: every number that defines the heat-slab problem, with validation.

The reference scenario of DESIGN.md §2 is the default of every field. A scenario
loads from YAML (`load_scenario`) with unknown keys and out-of-range values
refused by a `ScenarioError` that names the offending key.

Pure Python/numpy: no ROS import.
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, Mapping

import numpy as np


class ScenarioError(ValueError):
    """A scenario value is missing, unknown or out of range."""


@dataclass(frozen=True)
class Scenario:
    """The nonlinear 1-D heat slab problem (DESIGN.md §2).

    dT/dt = K(x,T) T_xx - eta T + sum_j b_j(x) (u_j + w_j),
    K(x,T) = k0 (1 + beta (T - T_ref)/T_scale)(1 + gamma x/L),
    dT/dx(0) = 0, T(L) = T_right; y = T(sensor nodes) + v.
    """

    # geometry and physics
    n_x: int = 100                     # nodes x_i = i L / n_x, i = 0..n_x-1
    length: float = 1.0                # L (scaled)
    k0: float = 0.01                   # diffusivity scale
    beta: float = 0.5                  # temperature dependence of K
    gamma: float = 0.2                 # spatial dependence of K
    t_ref: float = 100.0               # K(T) reference temperature [F]
    t_scale: float = 50.0              # K(T) temperature scale [F]
    eta: float = 0.002                 # convective loss coefficient [1/s]
    t_right: float = 150.0             # Dirichlet value at x = L [F]
    t_init: float = 100.0              # T(x, 0), known exactly [F]
    # actuators and sensors (positions as fractions of L)
    heater_centers: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)
    heater_sigma: float = 0.02         # Gaussian width, fraction of L
    sensor_positions: tuple[float, ...] = (0.1, 0.3, 0.5, 0.7, 0.9)
    u_min: float = -math.inf           # heater limits (applied by plant and LQR)
    u_max: float = math.inf
    # time
    dt: float = 0.25                   # [s]
    n_steps: int = 250                 # N
    # noise
    w_std: float = 0.3                 # process noise on heater inputs
    v_std: float = 1.0                 # sensor noise [F]
    # objective
    t_target: float = 150.0
    band: float = 3.0                  # +- band [F]
    k_band: int = 150                  # first step of the band / high weight
    q_late: float = 1.0
    q_early: float = 1e-5
    r_u: float = 0.1                   # input weight in the nominal cost
    # LQR/KF design weights (on sensor outputs)
    lqr_k_switch: int = 120
    lqr_q_late: float = 1.0            # Q_y = lqr_q_late I / n_y for k >= lqr_k_switch
    lqr_q_early: float = 0.1           # ... lqr_q_early I / n_y before
    lqr_r: float = 0.01                # R = lqr_r I
    # initial input guess for the optimizer
    u_init: float = 0.1

    # ------------------------------------------------------------------ checks
    def __post_init__(self) -> None:
        object.__setattr__(self, "heater_centers", tuple(float(c) for c in self.heater_centers))
        object.__setattr__(self, "sensor_positions", tuple(float(c) for c in self.sensor_positions))
        problems = list(_problems(self))
        if problems:
            raise ScenarioError("invalid scenario: " + "; ".join(problems))

    # ------------------------------------------------------------ derived data
    @property
    def n_u(self) -> int:
        return len(self.heater_centers)

    @property
    def n_y(self) -> int:
        return len(self.sensor_positions)

    @property
    def h(self) -> float:
        """Grid spacing L / n_x."""
        return self.length / self.n_x

    @property
    def horizon_s(self) -> float:
        return self.n_steps * self.dt

    def grid(self) -> np.ndarray:
        """Node positions x_i = i L / n_x (the Dirichlet node x = L is eliminated)."""
        return np.arange(self.n_x) * self.h

    def sensor_nodes(self) -> np.ndarray:
        """Index of the node nearest each sensor position."""
        x = self.grid()
        return np.array([int(np.argmin(np.abs(x - p * self.length))) for p in self.sensor_positions])

    def heater_profiles(self) -> np.ndarray:
        """b_j(x_i), shape (n_x, n_u): Gaussians integrating to 1 over the slab."""
        x = self.grid()[:, None]
        c = np.asarray(self.heater_centers)[None, :] * self.length
        s = self.heater_sigma * self.length
        return np.exp(-0.5 * ((x - c) / s) ** 2) / (s * math.sqrt(2.0 * math.pi))

    def q_weights(self) -> np.ndarray:
        """q_k for k = 0..N of the nominal cost (q_0 unused: T_0 is fixed)."""
        k = np.arange(self.n_steps + 1)
        return np.where(k >= self.k_band, self.q_late, self.q_early)

    def lqr_output_weights(self) -> np.ndarray:
        """Scalar Q_y multiplier per step k = 0..N (Q_y,k = w_k I / n_y)."""
        k = np.arange(self.n_steps + 1)
        return np.where(k >= self.lqr_k_switch, self.lqr_q_late, self.lqr_q_early) / self.n_y

    def heater_labels(self) -> list[str]:
        return [f"heater_{j}" for j in range(self.n_u)]

    def sensor_labels(self) -> list[str]:
        return [f"sensor_{j}" for j in range(self.n_y)]

    # ----------------------------------------------------------- (de)serialize
    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["heater_centers"] = list(self.heater_centers)
        d["sensor_positions"] = list(self.sensor_positions)
        return d

    def to_json(self) -> str:
        # math.inf is not JSON: encode as strings the loader understands
        return json.dumps({k: _encode(v) for k, v in self.to_dict().items()}, sort_keys=True)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "scenario") -> "Scenario":
        if not isinstance(data, Mapping):
            raise ScenarioError(f"{source}: expected a mapping of scenario keys, got {type(data).__name__}")
        known = {f.name: f for f in fields(cls)}
        unknown = sorted(set(data) - set(known), key=str)
        if unknown:
            raise ScenarioError(f"{source}: unknown key(s) {unknown}; known keys: {sorted(known)}")
        kwargs: dict[str, Any] = {}
        for key, value in data.items():
            kwargs[key] = _coerce(key, _decode(value), known[key].default, source)
        return cls(**kwargs)

    @classmethod
    def from_json(cls, text: str) -> "Scenario":
        return cls.from_dict(json.loads(text), "scenario JSON")

    def replace(self, **changes: Any) -> "Scenario":
        return dataclasses.replace(self, **changes)


# Fields that must agree between a design file and the plant it runs against.
PLANT_KEYS: tuple[str, ...] = (
    "n_x", "length", "dt", "n_steps", "heater_centers", "heater_sigma", "sensor_positions",
    "k0", "beta", "gamma", "t_ref", "t_scale", "eta", "t_right", "t_init",
)


def mismatches(a: Scenario, b: Scenario, keys: tuple[str, ...] = PLANT_KEYS) -> list[str]:
    """Human-readable list of keys where two scenarios differ (empty when they match)."""
    out = []
    for k in keys:
        va, vb = getattr(a, k), getattr(b, k)
        if isinstance(va, tuple):
            same = len(va) == len(vb) and all(math.isclose(p, q, rel_tol=1e-12, abs_tol=1e-12) for p, q in zip(va, vb))
        elif isinstance(va, float):
            same = math.isclose(va, vb, rel_tol=1e-12, abs_tol=1e-12)
        else:
            same = va == vb
        if not same:
            out.append(f"{k}: {va!r} != {vb!r}")
    return out


def load_scenario(path: str | Path | None) -> Scenario:
    """Load a YAML scenario file; None gives the shipped reference scenario.

    Only keys that differ from the reference need to be present.
    """
    if path is None:
        return Scenario()
    import yaml  # local import: only file loading needs PyYAML

    p = Path(path)
    if not p.is_file():
        raise ScenarioError(f"scenario file not found: {p}")
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{p}: not a YAML scenario file: {exc}") from None
    except OSError as exc:
        raise ScenarioError(f"{p}: cannot read: {exc}") from None
    if data is None:
        data = {}
    if isinstance(data, Mapping) and "scenario" in data and len(data) == 1:
        data = data["scenario"]
    return Scenario.from_dict(data, str(p))


# ---------------------------------------------------------------- internals
def _encode(v: Any) -> Any:
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return v


def _decode(v: Any) -> Any:
    if isinstance(v, str) and v.strip().lower() in ("inf", "+inf", ".inf", "-inf", "-.inf"):
        return -math.inf if v.strip().startswith("-") else math.inf
    return v


def _coerce(key: str, value: Any, default: Any, source: str) -> Any:
    def bad(expect: str) -> ScenarioError:
        return ScenarioError(f"{source}: {key} must be {expect}, got {value!r}")

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad("true or false")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise bad("an integer")
        return int(value)
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
            raise bad("a number")
        return float(value)
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or not value:
            raise bad("a non-empty list of numbers")
        try:
            return tuple(float(x) for x in value)
        except (TypeError, ValueError):
            raise bad("a non-empty list of numbers") from None
    return value


def _problems(s: Scenario):
    finite_pos = ["length", "k0", "dt", "heater_sigma", "t_scale", "lqr_r", "lqr_q_late", "lqr_q_early",
                  "q_late", "band"]
    for k in finite_pos:
        v = getattr(s, k)
        if not (math.isfinite(v) and v > 0):
            yield f"{k} must be a finite number > 0 (got {v!r})"
    for k in ["beta", "gamma", "eta", "t_ref", "t_right", "t_init", "t_target", "u_init"]:
        if not math.isfinite(getattr(s, k)):
            yield f"{k} must be finite (got {getattr(s, k)!r})"
    for k in ["w_std", "v_std", "q_early", "r_u"]:
        v = getattr(s, k)
        if not (math.isfinite(v) and v >= 0):
            yield f"{k} must be a finite number >= 0 (got {v!r})"
    if s.v_std <= 0:
        yield "v_std must be > 0 (the Kalman filter needs a positive sensor noise)"
    if s.n_x < 4:
        yield f"n_x must be >= 4 (got {s.n_x})"
    if s.n_steps < 2:
        yield f"n_steps must be >= 2 (got {s.n_steps})"
    if not 0 <= s.k_band <= s.n_steps:
        yield f"k_band must be in [0, n_steps] (got {s.k_band})"
    if not 0 <= s.lqr_k_switch <= s.n_steps:
        yield f"lqr_k_switch must be in [0, n_steps] (got {s.lqr_k_switch})"
    if not s.u_min < s.u_max:
        yield f"u_min must be < u_max (got {s.u_min}, {s.u_max})"
    if not s.u_min <= s.u_init <= s.u_max:
        yield f"u_init must lie within [u_min, u_max] (got {s.u_init})"
    for name in ("heater_centers", "sensor_positions"):
        pos = getattr(s, name)
        if not pos:
            yield f"{name} must not be empty"
        bad = [p for p in pos if not (math.isfinite(p) and 0.0 <= p <= 1.0)]
        if bad:
            yield f"{name} must be fractions of L in [0, 1] (got {bad})"
    if s.sensor_positions and s.n_x >= 4:
        nodes = [int(round(p * s.n_x)) for p in s.sensor_positions]
        if len(set(min(n, s.n_x - 1) for n in nodes)) != len(nodes):
            yield "two sensors map to the same grid node: refine n_x or move them"
    # K(x,T) must stay positive over the plausible temperature range
    for temp in (s.t_init, s.t_right, s.t_target):
        if 1 + s.beta * (temp - s.t_ref) / s.t_scale <= 0 or 1 + s.gamma <= 0:
            yield f"K(x,T) is not positive at T = {temp}: check beta/gamma/t_ref/t_scale"
            break
