"""The example rod as a native sep plant (numpy, batched) and the build of its test FMUs.

`RodPlant` has the physics of examples/fmu_rod/src/rod_model.h and the SAME fixed-step
integrator as sep's Model Exchange stepping and the FMU's own Co-Simulation doStep: classical
RK4, `substeps` steps per dt, inputs held, the stage arithmetic in the same order. So the FMU
plants (ME stepped by sep, CS stepped by the FMU) must equal it to round-off (the derivative
is the same formula evaluated by numpy instead of C).

`build(path, **variant)` builds an FMU with examples/fmu_rod/build_fmu.py, `session_fmu` once per
test session; `compiler()` says whether a C compiler is there, and `skip_without_toolchain()`
skips the calling test module (or test) without fmpy or a C compiler.
"""
from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "fmu_rod"


def build_module():
    """examples/fmu_rod/build_fmu.py as a module (it is a script, not a package)."""
    spec = importlib.util.spec_from_file_location("sep_example_build_fmu", EXAMPLE / "build_fmu.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def compiler() -> str | None:
    return build_module().compiler()


def skip_without_toolchain() -> None:
    """Skip (the calling module when called at import) without fmpy or a C compiler: the FMU
    tests build their FMUs from C source and run them with fmpy."""
    pytest.importorskip("fmpy", reason="the fmu plant needs fmpy (requirements.txt)")
    if compiler() is None:
        pytest.skip("no C compiler (cc, gcc or $CC): the FMU tests build their FMUs from C source",
                    allow_module_level=True)


def build(out: Path, **variant) -> Path:
    return build_module().build_fmu(out, **variant)


_BUILT: dict[str, Path] = {}


def session_fmu(tmp_path_factory, name: str = "rod", **variant) -> Path:
    """The FMU `name` (build_fmu's `variant`), built once per test session into its own folder
    (the test modules share it: each FMU is compiled once)."""
    if name not in _BUILT:
        _BUILT[name] = build(tmp_path_factory.mktemp(f"fmu_{name}") / f"{name}.fmu", **variant)
    return _BUILT[name]


class RodPlant:
    """The rod of examples/fmu_rod, natively (the plant protocol; see the module docstring)."""

    field_name = "T"
    field_unit = "F"
    field_is_state = True
    noise_on_inputs = True

    def __init__(self, n_nodes: int = 50, dt: float = 0.25, substeps: int = 4, length: float = 1.0,
                 k0: float = 0.002, beta: float = 0.5, t_ref: float = 100.0, t_scale: float = 50.0,
                 eta: float = 0.002, t_amb: float = 70.0, t_right: float = 150.0, t_init: float = 100.0,
                 heater_sigma: float = 0.05, heater_centers=(0.2, 0.5, 0.8), sensor_positions=(0.3, 0.55, 0.9),
                 q_left: float = 0.0):
        self.n_x = self.n_field = int(n_nodes)
        self.dt, self.substeps = float(dt), int(substeps)
        self.length, self.k0, self.beta, self.t_ref, self.t_scale = length, k0, beta, t_ref, t_scale
        self.eta, self.t_amb, self.t_right, self.t_init = eta, t_amb, t_right, t_init
        self.heater_sigma, self.q_left = heater_sigma, q_left
        self.heater_centers, self.sensor_positions = list(heater_centers), list(sensor_positions)
        self.n_u, self.n_y = len(self.heater_centers), len(self.sensor_positions)
        self.input_names = tuple(f"heater_{j + 1}" for j in range(self.n_u))
        self.output_names = tuple(f"sensor_{j + 1}" for j in range(self.n_y))
        self.h = length / self.n_x
        self.x = (np.arange(self.n_x) + 0.5) * self.h
        sig = heater_sigma * length
        z = (self.x[:, None] - np.asarray(self.heater_centers)[None, :] * length) / sig
        self.B = np.exp(-0.5 * z * z) / (sig * math.sqrt(2.0 * math.pi))
        self.sensors = np.clip(np.floor(np.asarray(self.sensor_positions) * self.n_x).astype(int), 0, self.n_x - 1)

    def config(self) -> dict:
        return {"n_nodes": self.n_x, "dt": self.dt, "substeps": self.substeps, "length": self.length, "k0": self.k0,
                "beta": self.beta, "t_ref": self.t_ref, "t_scale": self.t_scale, "eta": self.eta,
                "t_amb": self.t_amb, "t_right": self.t_right, "t_init": self.t_init,
                "heater_sigma": self.heater_sigma, "heater_centers": self.heater_centers,
                "sensor_positions": self.sensor_positions, "q_left": self.q_left}

    def conductivity(self, T):
        return self.k0 * (1.0 + self.beta * (T - self.t_ref) / self.t_scale)

    def rhs(self, T: np.ndarray, U: np.ndarray, q_left) -> np.ndarray:
        """dT/dt of every run, in the order of operations of rod_rhs (C)."""
        h, n = self.h, self.n_x
        K = self.conductivity(T)
        F = np.empty((T.shape[0], n + 1))
        F[:, 0] = -np.broadcast_to(q_left, (T.shape[0],))
        F[:, 1:n] = 0.5 * (K[:, :-1] + K[:, 1:]) * (T[:, 1:] - T[:, :-1]) / h
        F[:, n] = 0.5 * (K[:, -1] + self.conductivity(self.t_right)) * (self.t_right - T[:, -1]) / (0.5 * h)
        src = self.B[:, 0] * U[:, 0:1]
        for j in range(1, self.n_u):
            src = src + self.B[:, j] * U[:, j:j + 1]
        return (F[:, 1:] - F[:, :-1]) / h - self.eta * (T - self.t_amb) + src

    def initial_state(self, batch: int = 1) -> np.ndarray:
        return np.full((batch, self.n_x), self.t_init)

    def step(self, x, u, w=None, q_left=None) -> np.ndarray:
        T = np.atleast_2d(np.asarray(x, dtype=float)).copy()
        U = np.atleast_2d(np.asarray(u, dtype=float))
        if w is not None:
            U = U + np.atleast_2d(w)
        U = np.broadcast_to(U, (T.shape[0], self.n_u))
        q = self.q_left if q_left is None else np.asarray(q_left, dtype=float).reshape(-1)
        tau = self.dt / self.substeps
        for _ in range(self.substeps):
            k1 = self.rhs(T, U, q)
            k2 = self.rhs(T + (0.5 * tau) * k1, U, q)
            k3 = self.rhs(T + (0.5 * tau) * k2, U, q)
            k4 = self.rhs(T + tau * k3, U, q)
            T = T + (tau / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return T

    def observe(self, x):
        return np.atleast_2d(x)[:, self.sensors]

    def field(self, x):
        return x

    def field_coordinates(self) -> np.ndarray:
        xyz = np.zeros((self.n_x, 3))
        xyz[:, 0] = self.x
        return xyz


#: the short rod problem of the FMU product and node tests: heat the rod to 120 F +- 2 F over
#: t = 35..40 s, in steps of 0.5 s (8 RK4 substeps of the example's 0.0625 s)
ROD_PROBLEM = """\
n_steps: 80
target: 120.0
band: 2.0
band_window: [70, 80]
r_u: 1.0e-3
w_std: 0.05
v_std: 0.1
u_init: 0.3
lqr_r: 1.0e-3
"""


def rod_plant_yaml(interface: str, outputs: str = "sensor_1, sensor_2, sensor_3") -> str:
    """The `plant:` section of the example rod FMU (next to the scenario as rod.fmu) at dt = 0.5 s."""
    return f"""\
plant:
  type: fmu
  path: rod.fmu
  interface: {interface}
  inputs: [heater_1, heater_2, heater_3]
  outputs: [{outputs}]
  field: T
  field_name: temperature
  field_coordinates: "(i + 0.5) / n"
  dt: 0.5
  start_values: {{t_right: 120.0, n_substeps: 8}}
"""
