"""The plant protocol: everything sep needs from a simulator (the user's contract).

The method sees a plant only as a black box that can be started, stepped and observed. Any
object with the attributes and methods below is a plant; it does not subclass anything.

Description (attributes, fixed for the life of the object)::

    dt            float          time step [s]
    n_x           int            length of a state vector (what `step` advances)
    n_u, n_y      int            inputs (actuators) and outputs (sensors)
    n_field       int            nodes of the field the objective and reconstruction are about
    input_names   sequence[str]  n_u labels (message names, figure legends), unique
    output_names  sequence[str]  n_y labels, unique
    field_name    str            what the field is, e.g. "temperature" (PointCloud2 channel)
    field_unit    str            its unit, e.g. "F"

Behaviour (batched: a leading run axis M on every array; M = 1 for one run)::

    config() -> dict                          the plant's own keys, JSON-serializable, such that
                                              type(plant)(**config()) builds an identical plant
    initial_state(batch) -> (batch, n_x)      the known initial state, repeated
    step(x, u, w=None) -> (M, n_x)            x_{k+1} = f(x_k, u_k + w_k) for every run; a NEW
                                              array (x is not modified); u, w are (M, n_u) or
                                              (n_u,) (broadcast to every run); deterministic
    observe(x) -> (M, n_y)                    noise-free sensor outputs h(x)
    field(x) -> (M, n_field)                  the field (the state itself for the built-ins)
    field_coordinates() -> (n_field, 3)       node positions x, y, z in metres

Optional attributes (defaults in brackets)::

    grid_shape       tuple | None  [None]   the field is a regular grid of this shape (C order,
                                            prod = n_field): heat maps, sensor_msgs/Image
    field_is_state   bool  [False]          field(x) is x itself (saves a copy; the oracle's
                                            field map is then the identity)
    noise_on_inputs  bool  [True]           process noise enters through the inputs: step(x, u, w)
                                            equals step(x, u + w); w has n_u channels and its
                                            covariance in the ROM is B_k W B_k'
    n_w              int   [n_u]            noise channels when noise_on_inputs is false: w is
                                            (M, n_w) and enters f as the plant decides; the
                                            design then identifies the ROM's noise input map
                                            B_w,k from impulses on w as well (W -> B_w W B_w')
    frame_id         str   ["sep"]          the frame id of every message about this plant (its
                                            coordinates' frame), recorded in the design file
    device_capable   bool  [False]          step() also accepts the arrays of a numpy-compatible
                                            GPU module (CuPy) and returns that module's arrays,
                                            never converting to numpy: `--device cuda` may step
                                            it on a GPU (`sep_plant.device`)
    state_is_opaque  bool  [False]          states are copied and restarted but no arithmetic is
                                            done on them: a state row is data only the plant
                                            understands (a Co-Simulation FMU's serialized
                                            state). Rows must still be finite float64 of length
                                            n_x. sep then compares states by their outputs,
                                            never by value, and cannot use methods that do
                                            arithmetic on states (the EnKF belief, the
                                            full-order oracle)
    path_keys        tuple [()]             constructor keys that are file paths: a scenario
                                            resolves them relative to the scenario file's folder

Optional method::

    source_files() -> dict[str, str]          the files the plant's behaviour depends on, label ->
                                              absolute path (e.g. {"fmu": "/.../rod.fmu"}): the
                                              design file records their SHA-256 and refuses
                                              another file. Such a plant also reports each file
                                              in config() under a key K with its SHA-256 under
                                              K_sha256, so that scenarios compare files by
                                              content, not by path (`sep_plant.scenario`). Its
                                              class may define the classmethod
                                              rebuild(config, {label: bytes}) -> plant, which a
                                              cluster worker without the files calls with their
                                              shipped bytes (`sep_control.compute.engine`)

Optional method (uncertain initial state, `sep_plant.initial`)::

    initial_states(seeds) -> (M, n_x)         one initial state per integer seed, drawn from the
                                              plant's initial-state distribution (deterministic in
                                              the seed); initial_state stays the nominal one the
                                              design starts from (its mean, or another state the
                                              plant documents). The Monte Carlo and the plant node
                                              draw run r of seed s with `initial_seed(s, r)`; the
                                              design fits the filter's prior to sampled draws

State arrays must be copyable and restartable: a state is a float64 array; sep copies rows of
it (nominal snapshots) and later starts experiments from those copies, so `step` must depend on
nothing but its arguments (no hidden internal state, no random numbers of its own: every
random number comes in through `w`). A batch must give the same result as its runs stepped one
by one. `check_plant` (module `sep_plant.conformance`) tests all of this before any design work.
Plants need not be written in Python: `sep_plant.plants.fmu` runs an FMU (FMI 2.0/3.0) as one.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Mapping, Protocol, Sequence, runtime_checkable

import numpy as np


class PlantError(ValueError):
    """A plant does not meet the protocol (the message names the plant and the problem)."""


@runtime_checkable
class Plant(Protocol):
    """Structural type of a plant (see the module docstring for the contract)."""

    dt: float
    n_x: int
    n_u: int
    n_y: int
    n_field: int
    input_names: Sequence[str]
    output_names: Sequence[str]
    field_name: str
    field_unit: str

    def config(self) -> dict[str, Any]: ...

    def initial_state(self, batch: int) -> np.ndarray: ...

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray: ...

    def observe(self, x: np.ndarray) -> np.ndarray: ...

    def field(self, x: np.ndarray) -> np.ndarray: ...

    def field_coordinates(self) -> np.ndarray: ...


#: attributes and methods every plant must have (checked by name before anything is called)
REQUIRED_ATTRIBUTES = ("dt", "n_x", "n_u", "n_y", "n_field", "input_names", "output_names",
                       "field_name", "field_unit")
REQUIRED_METHODS = ("config", "initial_state", "step", "observe", "field", "field_coordinates")


@dataclass(frozen=True)
class PlantInfo:
    """What the rest of sep needs to know about a plant without running it: dimensions, names,
    time step, field description. Plain data (JSON round trip), so the design file, the scenario
    topic and bags carry it and no consumer has to import the plant's code."""

    dt: float
    n_x: int
    n_u: int
    n_y: int
    n_field: int
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    field_name: str = "value"
    field_unit: str = ""
    grid_shape: tuple[int, ...] | None = None
    field_is_state: bool = False
    noise_on_inputs: bool = True
    n_w: int | None = None             # noise channels (None: n_u, noise on the inputs)
    frame_id: str = "sep"              # frame id of the messages (the plant's optional frame_id)
    state_is_opaque: bool = False      # states are data only the plant understands (no arithmetic on them)

    @classmethod
    def of(cls, plant: Plant) -> "PlantInfo":
        """The description of a plant object.

        Parameters
        ----------
        plant : Plant
            Any object of the plant protocol; its optional attributes default as the module
            docstring says.

        Returns
        -------
        PlantInfo
            Dimensions, names, dt and field description, as plain data.
        """
        grid = getattr(plant, "grid_shape", None)
        return cls(dt=float(plant.dt), n_x=int(plant.n_x), n_u=int(plant.n_u), n_y=int(plant.n_y),
                   n_field=int(plant.n_field), input_names=tuple(str(n) for n in plant.input_names),
                   output_names=tuple(str(n) for n in plant.output_names),
                   field_name=str(plant.field_name), field_unit=str(plant.field_unit),
                   grid_shape=None if grid is None else tuple(int(g) for g in grid),
                   field_is_state=bool(getattr(plant, "field_is_state", False)),
                   noise_on_inputs=bool(getattr(plant, "noise_on_inputs", True)),
                   n_w=noise_channels(plant), frame_id=str(getattr(plant, "frame_id", "sep")),
                   state_is_opaque=bool(getattr(plant, "state_is_opaque", False)))

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["input_names"], d["output_names"] = list(self.input_names), list(self.output_names)
        d["grid_shape"] = None if self.grid_shape is None else list(self.grid_shape)
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "PlantInfo":
        """Parse and check a plant description (the inverse of `to_dict`).

        Parameters
        ----------
        d : mapping
            A plant description as `to_dict` writes it (JSON data); unknown keys are ignored.

        Returns
        -------
        PlantInfo

        Raises
        ------
        ValueError
            A key is missing or has a bad value (the message names it).
        """
        if not isinstance(d, Mapping):
            raise ValueError(f"plant description must be a mapping, got {type(d).__name__}")
        known = {f for f in cls.__dataclass_fields__}
        kw = {k: v for k, v in d.items() if k in known}
        for key in ("n_x", "n_u", "n_y", "n_field"):
            v = kw.get(key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"plant description: {key} must be a positive integer, got {v!r}")
        if not isinstance(kw.get("dt"), (int, float)) or isinstance(kw.get("dt"), bool) or not kw["dt"] > 0:
            raise ValueError(f"plant description: dt must be a number > 0, got {kw.get('dt')!r}")
        for key, n in (("input_names", kw["n_u"]), ("output_names", kw["n_y"])):
            names = kw.get(key)
            if not isinstance(names, (list, tuple)) or len(names) != n or not all(isinstance(x, str) for x in names):
                raise ValueError(f"plant description: {key} must be {n} strings, got {names!r}")
            kw[key] = tuple(names)
        if not isinstance(kw.get("state_is_opaque", False), bool):
            raise ValueError(f"plant description: state_is_opaque must be true or false, got {kw['state_is_opaque']!r}")
        if not isinstance(kw.get("frame_id", "sep"), str) or not kw.get("frame_id", "sep"):
            raise ValueError(f"plant description: frame_id must be a non-empty string, got {kw.get('frame_id')!r}")
        if kw.get("grid_shape") is not None:
            g = kw["grid_shape"]
            if not isinstance(g, (list, tuple)) or not all(isinstance(x, int) and x > 0 for x in g) \
                    or int(np.prod(g)) != kw["n_field"]:
                raise ValueError(f"plant description: grid_shape {g!r} does not hold n_field = {kw['n_field']} nodes")
            kw["grid_shape"] = tuple(g)
        return cls(**kw)

    @property
    def noise_dim(self) -> int:
        return self.n_u if self.n_w is None else int(self.n_w)

    @property
    def spatial_dims(self) -> int:
        """1, 2 or 3 for a grid plant (the grid's rank), else 1."""
        return len(self.grid_shape) if self.grid_shape else 1


# ------------------------------------------------------------------------------ helpers
def noise_channels(plant: Plant) -> int:
    """n_w: process-noise channels (n_u when the noise enters through the inputs)."""
    if getattr(plant, "noise_on_inputs", True):
        return int(plant.n_u)
    return int(getattr(plant, "n_w", plant.n_u))


def rollout(plant: Plant, x0: np.ndarray, U: np.ndarray, W: np.ndarray | None = None) -> np.ndarray:
    """States x_0..x_T of a batch stepped from x0 with inputs U (and process noise W).

    Parameters
    ----------
    plant : Plant
        The plant.
    x0 : ndarray, shape (M, n_x) or (n_x,)
        Initial states.
    U : ndarray, shape (M, T, n_u) or (T, n_u)
        Inputs u_0..u_{T-1} per run, or the same for every run.
    W : ndarray, shape (M, T, n_w), optional
        Process noise w_k per run; None: noise-free.

    Returns
    -------
    ndarray, shape (M, T+1, n_x)
        x_0..x_T of every run.
    """
    X0 = np.atleast_2d(x0)
    M = X0.shape[0]
    U = np.asarray(U, dtype=float)
    T = U.shape[-2]
    out = np.empty((M, T + 1, X0.shape[1]))
    out[:, 0] = X0
    for k in range(T):
        uk = U[k] if U.ndim == 2 else U[:, k]
        out[:, k + 1] = plant.step(out[:, k], uk, None if W is None else W[:, k])
    return out


def nominal_states(plant: Plant, U: np.ndarray) -> np.ndarray:
    """The noise-free nominal states from the plant's known initial state.

    Parameters
    ----------
    plant : Plant
        The plant.
    U : ndarray, shape (N, n_u)
        The nominal inputs ubar_0..ubar_{N-1}.

    Returns
    -------
    ndarray, shape (N+1, n_x)
        xbar_0..xbar_N.
    """
    return rollout(plant, plant.initial_state(1), U)[0]


def fields(plant: Plant, X: np.ndarray) -> np.ndarray:
    """`plant.field` over any leading axes.

    Parameters
    ----------
    plant : Plant
        The plant.
    X : ndarray, shape (..., n_x)
        States.

    Returns
    -------
    ndarray, shape (..., n_field)
        The field of every state.
    """
    return _over_leading_axes(plant.field, X)


def outputs(plant: Plant, X: np.ndarray) -> np.ndarray:
    """`plant.observe` over any leading axes.

    Parameters
    ----------
    plant : Plant
        The plant.
    X : ndarray, shape (..., n_x)
        States.

    Returns
    -------
    ndarray, shape (..., n_y)
        The noise-free outputs h(x) of every state.
    """
    return _over_leading_axes(plant.observe, X)


def _over_leading_axes(fn, X: np.ndarray) -> np.ndarray:
    """A batched plant method (M, n_x) -> (M, m) applied over any leading axes of X."""
    lead = X.shape[:-1]
    return fn(X.reshape(-1, X.shape[-1])).reshape(lead + (-1,))


def clip_inputs(u: np.ndarray, lo: np.ndarray | float, hi: np.ndarray | float) -> np.ndarray:
    """Inputs clipped to the limits [lo, hi] per channel.

    Parameters
    ----------
    u : ndarray, shape (..., n_u)
        Inputs.
    lo, hi : float or ndarray, shape (n_u,)
        Lower and upper limits (-inf / inf: none).

    Returns
    -------
    ndarray, shape (..., n_u)
        The clipped inputs; `u` itself (not a copy) when every limit is infinite.
    """
    if np.all(np.isinf(lo)) and np.all(np.isinf(hi)):
        return u
    return np.clip(u, lo, hi)


def clip_rate(u: np.ndarray, prev: np.ndarray | None, du_max: np.ndarray | float) -> np.ndarray:
    """Inputs clipped to the rate limits |u_k - u_{k-1}| <= du_max per channel (applied after
    `clip_inputs`: with u_{k-1} inside the box the result stays inside it).

    Parameters
    ----------
    u : ndarray, shape (..., n_u)
        Inputs u_k (already inside the box).
    prev : ndarray, shape (..., n_u), or None
        The inputs applied at the step before, u_{k-1}; None (step 0): no rate limit.
    du_max : float or ndarray, shape (n_u,)
        Largest change per step (inf: none).

    Returns
    -------
    ndarray, shape (..., n_u)
        The clipped inputs; `u` itself (not a copy) when there is no limit or no previous input.
    """
    if prev is None or np.all(np.isinf(du_max)):
        return u
    return np.clip(u, prev - du_max, prev + du_max)


def rate_feasible(U: np.ndarray, du_max: np.ndarray | float, tol: float = 1e-9) -> np.ndarray:
    """Whether input sequences keep |u_k - u_{k-1}| <= du_max (+ tol) for every k >= 1 and channel.

    Parameters
    ----------
    U : ndarray, shape (..., T, n_u)
        Input sequences u_0..u_{T-1} (any leading run axes).
    du_max : float or ndarray, shape (n_u,)
    tol : float
        Absolute slack (the limits are met to rounding).

    Returns
    -------
    ndarray of bool, shape (...)
    """
    dU = np.abs(np.diff(U, axis=-2))
    return np.all(dU <= np.asarray(du_max) + tol, axis=(-2, -1))


def rate_clip_sequence(U: np.ndarray, du_max: np.ndarray | float, prev: np.ndarray | None = None) -> np.ndarray:
    """A sequence U (T, n_u) made rate-feasible forward in time: u_k = clip_rate(u_k, u_{k-1}) for
    k = 0..T-1 (u_{-1} = prev; None: u_0 is kept). A copy; U itself when there is no limit."""
    if np.all(np.isinf(du_max)):
        return U
    out = np.array(U, dtype=float)
    last = prev
    for k in range(out.shape[-2]):
        out[..., k, :] = clip_rate(out[..., k, :], last, du_max)
        last = out[..., k, :]
    return out


@dataclass
class GridGeometry:
    """Node coordinates of a regular grid (helper for plants on structured grids)."""

    axes: tuple[np.ndarray, ...]          # node positions along each axis [m]
    shape: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        self.shape = tuple(len(a) for a in self.axes)

    def coordinates(self) -> np.ndarray:
        """(prod(shape), 3) x, y, z of every node in C order (missing axes are 0)."""
        mesh = np.meshgrid(*self.axes, indexing="ij")
        xyz = np.zeros((int(np.prod(self.shape)), 3))
        for i, m in enumerate(mesh):
            xyz[:, i] = m.ravel()
        return xyz
