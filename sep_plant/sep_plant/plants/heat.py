"""Built-in 2-D and 3-D heat plants: `HeatPlate` (64 x 64) and `HeatBlock` (24 x 24 x 24).

The same physics on a box [0, L_1] x ... x [0, L_d] (per unit heat capacity)::

    dT/dt = div(K(T) grad T) - eta (T - t_amb) - r (T_K^4 - t_amb,K^4) + sum_j b_j(x) (u_j + w_j)
    K(T) = k0 (1 + beta (T - t_ref)/t_scale)                     (the slab's law)
    y = T(sensor nodes) + v

* Units. Temperature in `unit` (default F, the slab's convention), lengths in metres, time in
  seconds; k0 [m^2/s] is a diffusivity, eta [1/s] a convective loss rate, u_j the heating rate
  of lamp j in unit * m^d / s (each b_j integrates to 1 over the box, as the slab's heaters).
  Why F and no radiation by default: the plates and blocks are the paper's slab grown to 2-D
  and 3-D, so the reference scenario (100 F -> 150 +- 3 F, dt = 0.25 s, its noise and weights)
  applies unchanged, and between 100 and 150 F radiation is a nearly linear loss that eta
  already models. Radiation is what makes rapid thermal processing (RTP) of wafers strongly
  nonlinear (T^4 at 900-1400 K); set r > 0 for that, best with unit "K". Radiation needs
  absolute temperature, so the plant converts: T_K = T + 273.15 (unit "C"), (T + 459.67) 5/9
  ("F"), T ("K"); r = eps sigma n_faces / (rho c d) [1/(s K^3)] (kelvin-based: loss in K/s, in
  the plant's unit it is scaled by 9/5 for F). A silicon wafer (eps 0.7, two faces, rho c d =
  1605 J/(m^2 K)) has r = 4.9e-11; its linearized loss rate 4 r T_K^3 is 0.2/s at 1000 K.
  In the block the losses are volumetric, the same lumped model as the plate's (a surface
  loss would be a Robin boundary condition, not modelled).
* Conduction is in flux form, div(K grad T), the physical law for a temperature-dependent
  conductivity: an insulated box without losses conserves its heat exactly (also for
  beta != 0), and for beta = 0 it is the slab's K T_xx. Face conductivities are averages of
  the nodes', K_{i+1/2} = (K_i + K_{i+1})/2 (= K at the mean temperature, K being linear).
* Boundaries. Faces named in `boundary_temperatures` ("x_min", "x_max", "y_min", "y_max",
  "z_min", "z_max") are held at that temperature (Dirichlet; the face node is eliminated);
  all others are insulated (ghost node). Vertex-centred grid per axis (`adi.Axis`): the slab's
  discretization (x_i = i L/n for an axis insulated at 0 and held at L).
* Time step: the slab's backward Euler with K frozen at T_k (and the radiation linearized at
  T_k), split by Douglas ADI (`adi.douglas_step`): per step one batched tridiagonal solve per
  axis over every line of every run (LAPACK dptsv, or a vectorized Thomas sweep). First order in dt; steady states are exact; a field
  uniform along the insulated axes evolves exactly like the 1-D slab.

Defaults and why (a control engineer's reading):
* HeatPlate: 1 m x 1 m, 64 x 64, insulated except the edge x = L held at 150 F: the paper's slab
  extruded in y (same k0, beta, t_ref, t_scale, t_init = 100 F). Lamps: a 3 x 3 grid at 1/6,
  1/2, 5/6 of each side, sigma 0.1 of a side (overlapping zones as in multi-zone RTP lamp
  heads; narrow ones would leave hot spots, a 2-D point source having a log singularity).
  Five point sensors (pyrometers): the centre and the four quadrant centres. n_y = 5 < n_u = 9:
  the zones between sensors must be estimated from the model (partially observed).
  Time scales: diffusion L^2/k0 = 100 s, across a lamp zone (L/3)^2/k0 = 11 s, convective loss
  1/eta = 500 s (to t_amb = 70 F). dt = 0.25 s resolves the zone time with ~45 steps while
  k0 dt/h^2 = 10 (an explicit step would need dt < 0.006 s). Open-loop drift: a constant
  u_j = 0.05 brings the noise-free plate to 150-152 F at 62.5 s, but with the reference lamp
  noise (w ~ N(0, 0.3^2) per lamp and step) the deviation's std reaches 2.6 F and 68 % of
  runs leave the +-3 F band (40 runs): the field has to be estimated and regulated.
* HeatBlock: 1 m cube, 24^3, insulated except the bottom face z = 0 held at 150 F (the slab
  turned vertical); the 3 x 3 lamps sit on the top face z = L (Gaussians centred on the face,
  absorbed within ~0.2 m) and heat the interior only by conduction (depth diffusion
  (L/2)^2/k0 = 25 s, before the band window at 37.5 s). sigma 0.2, twice the plate's: a lamp's
  energy spreads into a half-ball instead of a disc, and at 0.2 the centre lamp's peak heating
  density per unit input (16 per m^3) equals the plate's (16 per m^2), so the same input noise
  kicks the surface by the same ~1.2 F per step (at 0.1 it would be ~9 F). Sensors: four
  pyrometers on the top face (quadrant centres) and one thermocouple at the block's centre;
  the filter reconstructs 13824 nodes from five sensors. Open loop (u_j = 0.03: 149-153 F
  noise-free at 62.5 s) every one of 20 noisy runs leaves the band (deviation std up to 5.8 F:
  the heat content random-walks, the held face being far from the lamps).
Pure numpy/scipy: no ROS import.
"""
from __future__ import annotations

from types import MappingProxyType
from typing import Any, Mapping, Sequence

import numpy as np

from sep_plant.plants import adi, blocks, keys
from sep_plant.initial import offset_states, spread_key
from sep_plant.plants.backend import DeviceConstants, namespace

#: T_K = (T + offset) * scale for each temperature unit
UNITS: dict[str, tuple[float, float]] = {"K": (0.0, 1.0), "C": (273.15, 1.0), "F": (459.67, 5.0 / 9.0)}

_LAMPS_2D = tuple((a, b) for a in (1 / 6, 1 / 2, 5 / 6) for b in (1 / 6, 1 / 2, 5 / 6))
_LAMPS_3D = tuple((a, b, 1.0) for a, b in _LAMPS_2D)
_SENSORS_2D = ((0.5, 0.5), (0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75))
_SENSORS_3D = ((0.25, 0.25, 1.0), (0.75, 0.25, 1.0), (0.25, 0.75, 1.0), (0.75, 0.75, 1.0), (0.5, 0.5, 0.5))


# ------------------------------------------------------------------------------ shared plumbing
class GridPlant:
    """What the grid plants share: a regular grid (`adi.Grid`), Gaussian actuators, point
    sensors at the nearest nodes, batched inputs, the protocol's description. Subclasses set
    the grid, `_B` (n_x, n_u) and `_sensors`, and implement `_step(T, src)` on (M, *shape)."""

    field_is_state = True
    noise_on_inputs = True
    #: step() accepts CuPy arrays and steps them on their GPU (`sep_plant.device`)
    device_capable = True
    #: line solver of `adi.douglas_step` ("auto", "lapack", "thomas" or "pcr"; same results to
    #: round-off; on a GPU array module "auto" and "lapack" are "pcr")
    solver = "auto"
    #: a batch is stepped in blocks of at most this many nodes (`blocks.step_in_blocks`)
    block_nodes = blocks.BLOCK_NODES

    grid: adi.Grid
    _B: np.ndarray
    _sensors: np.ndarray

    def _describe(self, input_prefix: str, n_u: int, n_y: int) -> None:
        self.grid_shape = self.grid.shape
        self.n_x = self.n_field = self.grid.size
        self.n_u, self.n_y = n_u, n_y
        self.input_names = tuple(f"{input_prefix}_{j}" for j in range(n_u))
        self.output_names = tuple(f"sensor_{j}" for j in range(n_y))
        self._device = DeviceConstants()                                   # device copies of _B

    # ------------------------------------------------------------- protocol
    def field_coordinates(self) -> np.ndarray:
        """(n_x, 3) node positions [m], C order matching grid_shape."""
        return self.grid.coordinates()

    def sensor_nodes(self) -> np.ndarray:
        """Flat index of the node nearest each sensor position."""
        return self._sensors.copy()

    def observe(self, x: np.ndarray) -> np.ndarray:
        """Noise-free sensor outputs: the field at the sensor nodes."""
        return x[..., self._sensors]

    def field(self, x: np.ndarray) -> np.ndarray:
        """The field is the state."""
        return x

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """x_{k+1} = f(x_k, u_k + w_k) for every run of the batch (a new array)."""
        X, src, single = self._batch(x, u, w)
        T = X.reshape((X.shape[0],) + self.grid.shape)
        out = blocks.step_in_blocks(self._step, T, src, self.block_nodes).reshape(X.shape)
        return out[0] if single else out

    def rhs(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """dx/dt of the semi-discrete system (method of lines) at x: what `step` integrates,
        for fine-step references and tests (not part of the protocol)."""
        X, src, single = self._batch(x, u, w)
        out = self._rhs(X.reshape((X.shape[0],) + self.grid.shape), src).reshape(X.shape)
        return out[0] if single else out

    # ------------------------------------------------------------- helpers
    def _batch(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, bool]:
        """States (M, n_x), the source sum_j b_j (u_j + w_j) as (M, *shape), and whether x was 1-D."""
        xp = namespace(x, u, w)
        single = np.ndim(x) == 1
        X = xp.atleast_2d(xp.asarray(x, dtype=float))
        U = xp.atleast_2d(xp.asarray(u, dtype=float))
        if w is not None:
            U = U + xp.atleast_2d(xp.asarray(w, dtype=float))
        M = X.shape[0]
        if X.shape[1] != self.n_x or U.shape[-1] != self.n_u or U.shape[0] not in (1, M):
            raise ValueError(f"step: expected states (*, {self.n_x}) and inputs (*, {self.n_u}), "
                             f"got {X.shape} and {U.shape}")
        src = U @ self._device.get(xp, "B", lambda: self._B).T            # (M or 1, n_x)
        src = xp.broadcast_to(src, (M, self.n_x)).reshape((M,) + self.grid.shape)
        return X, src, single

    def _step(self, T: np.ndarray, src: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _rhs(self, T: np.ndarray, src: np.ndarray) -> np.ndarray:
        raise NotImplementedError


def check_nodes(name: str, value: Any, ndim: int) -> tuple[int, ...]:
    """`ndim` node counts, each >= 3."""
    if not isinstance(value, (list, tuple)) or len(value) != ndim:
        raise keys.PlantConfigError(f"{name} must be a list of {ndim} node counts, got {value!r}")
    return tuple(keys.integer(f"{name}[{i}]", v, lo=3, hi=4096) for i, v in enumerate(value))


def check_lengths(name: str, value: Any, ndim: int) -> tuple[float, ...]:
    """`ndim` side lengths [m], each > 0."""
    if not isinstance(value, (list, tuple)) or len(value) != ndim:
        raise keys.PlantConfigError(f"{name} must be a list of {ndim} lengths [m], got {value!r}")
    return tuple(keys.positive(f"{name}[{i}]", v) for i, v in enumerate(value))


def check_faces(name: str, value: Any, ndim: int) -> dict[str, float]:
    """{face: value} for faces of an ndim box (x_min, x_max, y_min, ...)."""
    if not isinstance(value, Mapping):
        raise keys.PlantConfigError(f"{name} must be a mapping face -> value (faces "
                                    f"{', '.join(adi.FACES[:2 * ndim])}), got {value!r}")
    out = {}
    for face, v in value.items():
        if face not in adi.FACES[:2 * ndim]:
            raise keys.PlantConfigError(f"{name}: unknown face {face!r}; faces are "
                                        f"{', '.join(adi.FACES[:2 * ndim])}")
        out[face] = keys.number(f"{name}.{face}", v)
    return {f: out[f] for f in adi.FACES if f in out}                   # canonical order


def actuator_profiles(grid: adi.Grid, centers: Sequence[Sequence[float]], sigma: float,
                      name: str, *, normalize: str) -> np.ndarray:
    """Gaussian actuators b_j(x_i), (n_x, n_u): centres and sigma as fractions of each side.

    normalize "integral": the grid quadrature of b_j is 1 (sum_i w_i b_j(x_i) cell_volume = 1,
    exact: total input energy is dt sum_j u_j); "peak": b_j = 1 at the centre."""
    B = grid.gaussians(centers, sigma)
    if normalize == "integral":
        mass = (grid.weights().ravel() * grid.cell_volume) @ B
        if np.any(mass <= 1e-12 * grid.cell_volume):
            j = int(np.argmin(mass))
            raise keys.PlantConfigError(f"{name}[{j}] has no weight on the grid: widen the sigma or refine")
        B = B / mass
    return B


# ------------------------------------------------------------------------------ heat
class _Heat(GridPlant):
    """Heat conduction on a 2-D/3-D box (see the module docstring)."""

    field_name = "temperature"
    _NDIM = 0

    def _setup(self, nodes, lengths, k0, beta, t_ref, t_scale, eta, t_amb, radiation, unit,
               boundary_temperatures, t_init, lamp_centers, lamp_sigma, sensor_positions, dt) -> None:
        d = self._NDIM
        self.nodes = check_nodes("nodes", nodes, d)
        self.lengths = check_lengths("lengths", lengths, d)
        self.k0 = keys.positive("k0", k0)
        self.beta = keys.number("beta", beta)
        self.t_ref = keys.number("t_ref", t_ref)
        self.t_scale = keys.positive("t_scale", t_scale)
        self.eta = keys.number("eta", eta, lo=0.0)
        self.t_amb = keys.number("t_amb", t_amb)
        self.radiation = keys.number("radiation", radiation, lo=0.0)
        if not isinstance(unit, str) or unit not in UNITS:
            raise keys.PlantConfigError(f"unit must be one of {', '.join(UNITS)}, got {unit!r}")
        self.unit = unit
        self.boundary_temperatures = check_faces("boundary_temperatures", boundary_temperatures, d)
        self.t_init = keys.number("t_init", t_init)
        self.lamp_centers = keys.points("lamp_centers", lamp_centers, d)
        self.lamp_sigma = keys.positive("lamp_sigma", lamp_sigma)
        self.sensor_positions = keys.points("sensor_positions", sensor_positions, d)
        self.dt = keys.positive("dt", dt)
        self.field_unit = unit
        self._offset, self._scale = UNITS[unit]
        temps = {"t_init": self.t_init, "t_amb": self.t_amb,
                 **{f"boundary_temperatures.{f}": v for f, v in self.boundary_temperatures.items()}}
        for name, temp in temps.items():
            if (temp + self._offset) * self._scale <= 0.0:
                raise keys.PlantConfigError(f"{name} = {temp:g} {unit} is below absolute zero")
            if self._conductivity(temp) <= 0.0:
                raise keys.PlantConfigError(f"K(T) = k0 (1 + beta (T - t_ref)/t_scale) is not positive at "
                                            f"{name} = {temp:g}: check beta/t_ref/t_scale")
        self.grid = adi.axes_for(self.nodes, self.lengths, self.boundary_temperatures)
        self._held = {f: adi.Held(v, self._conductivity(v)) for f, v in self.boundary_temperatures.items()}
        self._B = actuator_profiles(self.grid, self.lamp_centers, self.lamp_sigma, "lamp_centers",
                                    normalize="integral")
        self._sensors = self.grid.nearest_nodes(self.sensor_positions)
        keys.distinct("sensor_positions", list(self._sensors))
        self._t_amb_k4 = self._kelvin(self.t_amb) ** 4
        self._describe("lamp", len(self.lamp_centers), len(self.sensor_positions))

    # ------------------------------------------------------------- description
    def config(self) -> dict[str, Any]:
        return {"nodes": list(self.nodes), "lengths": list(self.lengths), "k0": self.k0, "beta": self.beta,
                "t_ref": self.t_ref, "t_scale": self.t_scale, "eta": self.eta, "t_amb": self.t_amb,
                "radiation": self.radiation, "unit": self.unit,
                "boundary_temperatures": dict(self.boundary_temperatures), "t_init": self.t_init,
                "lamp_centers": [list(c) for c in self.lamp_centers], "lamp_sigma": self.lamp_sigma,
                "sensor_positions": [list(p) for p in self.sensor_positions], "dt": self.dt,
                **spread_key(self.initial_spread)}

    def lamp_profiles(self) -> np.ndarray:
        """b_j(x_i), (n_x, n_u): Gaussians each integrating to 1 over the box [1/m^d]."""
        return self._B.copy()

    def heat_weights(self) -> np.ndarray:
        """(n_x,) quadrature weights [m^d]: sum_i weights_i T_i is the heat content integral of T dV
        (per unit heat capacity); an insulated, lossless box changes it by dt sum_j u_j per step."""
        return self.grid.weights().ravel() * self.grid.cell_volume

    def initial_state(self, batch: int = 1) -> np.ndarray:
        """T = t_init everywhere: (batch, n_x)."""
        return np.full((batch, self.n_x), self.t_init)

    def initial_states(self, seeds) -> np.ndarray:
        """(M, n_x): one initial state per seed, the known one plus a uniform offset of std
        `initial_spread` (`sep_plant.initial.offset_states`; 0: the known state exactly)."""
        return offset_states(self.initial_state(1)[0], self.initial_spread, seeds)

    # ------------------------------------------------------------- physics
    def _conductivity(self, T):
        """K(T) = k0 (1 + beta (T - t_ref)/t_scale) [m^2/s] (2 passes over a field)."""
        a = self.k0 * self.beta / self.t_scale
        return a * T + (self.k0 - a * self.t_ref)

    def _kelvin(self, T):
        return (T + self._offset) * self._scale

    def _losses(self, T: np.ndarray, src: np.ndarray) -> tuple[np.ndarray, np.ndarray | float]:
        """g(T) = sources - eta (T - t_amb) - r (T_K^4 - t_amb,K^4) and lam = -dg/dT = eta + 4 r T_K^3."""
        g = src - self.eta * (T - self.t_amb)
        if self.radiation == 0.0:
            return g, self.eta
        Tk = self._kelvin(T)
        Tk3 = Tk * Tk * Tk
        g -= (self.radiation / self._scale) * (Tk3 * Tk - self._t_amb_k4)
        return g, self.eta + 4.0 * self.radiation * Tk3

    def _step(self, T: np.ndarray, src: np.ndarray) -> np.ndarray:
        g, lam = self._losses(T, src)
        return adi.douglas_step(self.grid, T, self._conductivity, self._held, g, lam, self.dt, self.solver)

    def _rhs(self, T: np.ndarray, src: np.ndarray) -> np.ndarray:
        g, _ = self._losses(T, src)
        return adi.diffusion(self.grid, T, self._conductivity, self._held) + g


class HeatPlate(_Heat):
    """Nonlinear heat conduction in a plate with a 3 x 3 lamp array (2-D; module docstring)."""

    _NDIM = 2

    def __init__(self, nodes: Sequence[int] = (64, 64), lengths: Sequence[float] = (1.0, 1.0),
                 k0: float = 0.01, beta: float = 0.5, t_ref: float = 100.0, t_scale: float = 50.0,
                 eta: float = 0.002, t_amb: float = 70.0, radiation: float = 0.0, unit: str = "F",
                 boundary_temperatures: Mapping[str, float] = MappingProxyType({"x_max": 150.0}),
                 t_init: float = 100.0, lamp_centers: Sequence[Sequence[float]] = _LAMPS_2D,
                 lamp_sigma: float = 0.1, sensor_positions: Sequence[Sequence[float]] = _SENSORS_2D,
                 dt: float = 0.25, initial_spread: float = 0.0):
        self._setup(nodes, lengths, k0, beta, t_ref, t_scale, eta, t_amb, radiation, unit,
                    boundary_temperatures, t_init, lamp_centers, lamp_sigma, sensor_positions, dt)
        self.initial_spread = keys.number("initial_spread", initial_spread, lo=0.0)


class HeatBlock(_Heat):
    """Nonlinear heat conduction in a block heated by lamps on its top face (3-D; module docstring)."""

    _NDIM = 3

    def __init__(self, nodes: Sequence[int] = (24, 24, 24), lengths: Sequence[float] = (1.0, 1.0, 1.0),
                 k0: float = 0.01, beta: float = 0.5, t_ref: float = 100.0, t_scale: float = 50.0,
                 eta: float = 0.002, t_amb: float = 70.0, radiation: float = 0.0, unit: str = "F",
                 boundary_temperatures: Mapping[str, float] = MappingProxyType({"z_min": 150.0}),
                 t_init: float = 100.0, lamp_centers: Sequence[Sequence[float]] = _LAMPS_3D,
                 lamp_sigma: float = 0.2, sensor_positions: Sequence[Sequence[float]] = _SENSORS_3D,
                 dt: float = 0.25, initial_spread: float = 0.0):
        self._setup(nodes, lengths, k0, beta, t_ref, t_scale, eta, t_amb, radiation, unit,
                    boundary_temperatures, t_init, lamp_centers, lamp_sigma, sensor_positions, dt)
        self.initial_spread = keys.number("initial_spread", initial_spread, lo=0.0)


__all__ = ["GridPlant", "HeatBlock", "HeatPlate", "UNITS", "actuator_profiles", "check_faces",
           "check_lengths", "check_nodes"]
