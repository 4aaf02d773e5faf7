"""`FMUPlant`: a simulator exported as an FMU (FMI 2.0 or 3.0) as a sep plant.

Scenario keys (``plant: {type: fmu, ...}``; docs/plants.md)::

    path               the .fmu file (relative to the scenario file's folder)          required
    dt                 plant step [s]                       default: DefaultExperiment stepSize
    inputs             input variables driven by sep (u)    default: every Real input not in noise_inputs
    outputs            sensor variables (y = h(x))          default: every Real output
    field              the field: an array name (T -> T[1]..T[n], or an FMI 3.0 array) or a
                       list of variable names               default: the states (ME), the outputs (CS)
    field_coordinates  node positions (sep_plant.plants.fmu.layout)   default: node i at x = i m
    grid_shape         the field's grid (1-3 axes)          default: the array's shape if 2-D/3-D
    field_name, field_unit   default: the array's name (else "value"), its declared unit
    start_values       {name: value}: parameters and start values set before initialization
    noise_inputs       input variables that take the process noise w (default: none, the
                       noise adds to the inputs: u + w)
    interface          auto | model_exchange | co_simulation    (auto: Model Exchange if present)
    substeps           RK4 steps per dt (Model Exchange only)   default 1
    start_time         default: DefaultExperiment startTime, else 0
    path_sha256        the FMU's SHA-256 (config() fills it in; when given, another file is refused)

Model Exchange: the state is the FMU's continuous-state vector, stepped by sep with classical
RK4 (`exchange`); the model must not depend on time explicitly (it is evaluated at start_time)
and must have no event indicators. Co-Simulation (FMU state get/set and serialization needed):
the state is opaque, the FMU's serialized state in a float64 row (`cosim`; state_is_opaque).
One FMU instance per plant and process steps every run of a batch; a plant pickles as its
configuration and the FMU's bytes (`from_bytes` rebuilds it where the file is absent).
Pure numpy/ctypes (fmpy): no ROS import.
"""
from __future__ import annotations

import os
import re
import threading
import weakref
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from sep_plant.plants import keys
from sep_plant.plants.fmu import archive, layout
from sep_plant.plants.fmu.binding import FMICallError, open_instance
from sep_plant.plants.fmu.cosim import HEADER, CoSimStepper
from sep_plant.plants.fmu.description import Description, Selection, describe, platform_binary
from sep_plant.plants.fmu.exchange import ExchangeStepper

INTERFACE_KEYS = ("auto", "model_exchange", "co_simulation")
FMPY_HINT = "the fmu plant needs fmpy: pip install fmpy==0.3.32 (it is in sep's requirements.txt)"


class FMUError(keys.PlantConfigError):
    """An FMU cannot serve as a plant: the message names the FMU and every problem."""


def _names(key: str, value: Any, *, allow_none: bool = True) -> list[str] | None:
    if value is None and allow_none:
        return None
    if isinstance(value, str) or not isinstance(value, (list, tuple)) or not value \
            or not all(isinstance(v, str) and v for v in value):
        raise keys.PlantConfigError(f"{key} must be a non-empty list of FMU variable names, got {value!r}")
    if len(set(value)) != len(value):
        raise keys.PlantConfigError(f"{key} names a variable twice: {list(value)!r}")
    return list(value)


class FMUPlant:
    """An FMU as a plant of the plant protocol (sep_plant.protocol).

    Parameters
    ----------
    path : the .fmu file (absolute, or relative to the working directory; a scenario makes it
        relative to the scenario file).
    dt : plant step [s]; default the FMU's DefaultExperiment stepSize.
    inputs, outputs : FMU variable names of u and y (Real scalars); defaults: every Real input
        (not in `noise_inputs`) and every Real output.
    field : an array's name or a list of variable names; default the states (Model Exchange)
        or the outputs (Co-Simulation).
    field_coordinates, grid_shape : where the field's nodes are (`sep_plant.plants.fmu.layout`).
    field_name, field_unit : defaults: the array's name (else "value") and its declared unit.
    start_values : {name: value} set before initialization (parameters, start values).
    noise_inputs : input variables that take the process noise w; default None: w adds to u.
    interface : "auto" (Model Exchange if present), "model_exchange" or "co_simulation".
    substeps : RK4 steps per dt (Model Exchange only; default 1).
    start_time : default the DefaultExperiment startTime, else 0.
    path_sha256 : the SHA-256 the file must have (config() fills it in).

    Raises
    ------
    FMUError (a PlantConfigError) naming the FMU and every problem found.
    """

    #: constructor keys that are file paths (a scenario resolves them relative to its folder)
    path_keys = ("path",)

    def __init__(self, path: str, dt: float | None = None, inputs: Sequence[str] | None = None,
                 outputs: Sequence[str] | None = None, field: str | Sequence[str] | None = None,
                 field_coordinates: Any = None, grid_shape: Sequence[int] | None = None,
                 field_name: str | None = None, field_unit: str | None = None,
                 start_values: Mapping[str, Any] | None = None, noise_inputs: Sequence[str] | None = None,
                 interface: str = "auto", substeps: int | None = None, start_time: float | None = None,
                 path_sha256: str | None = None):
        self._check_keys(path, inputs, outputs, field, start_values, noise_inputs, interface, substeps,
                         path_sha256, field_name, field_unit)
        self._field_coordinates_key, self._grid_key = field_coordinates, grid_shape
        desc = self._read()
        self._resolve(desc, dt, start_time, field_name, field_unit)
        self._lock = threading.RLock()
        self._open()

    # ------------------------------------------------------------------ keys
    def _check_keys(self, path, inputs, outputs, field, start_values, noise_inputs, interface, substeps,
                    path_sha256, field_name, field_unit) -> None:
        if not isinstance(path, (str, os.PathLike)) or not str(path):
            raise keys.PlantConfigError(f"path must be the FMU file (a string), got {path!r}")
        self.path = os.path.abspath(os.path.expanduser(str(path)))
        self._inputs_key = _names("inputs", inputs)
        self._outputs_key = _names("outputs", outputs)
        self._noise_key = _names("noise_inputs", noise_inputs)
        if field is not None and not (isinstance(field, str) and field):
            field = _names("field", field)
        self._field_key = field
        if start_values is None:
            start_values = {}
        if not isinstance(start_values, Mapping) or not all(isinstance(k, str) for k in start_values):
            raise keys.PlantConfigError(f"start_values must be a mapping of FMU variable names to values, "
                                        f"got {start_values!r}")
        self.start_values = dict(start_values)
        if interface not in INTERFACE_KEYS:
            raise keys.PlantConfigError(f"interface must be one of {', '.join(INTERFACE_KEYS)}, got {interface!r}")
        self._interface_key = interface
        self._substeps_key = None if substeps is None else keys.integer("substeps", substeps, lo=1, hi=100_000)
        if path_sha256 is not None and not (isinstance(path_sha256, str) and re.fullmatch(r"[0-9a-f]{64}", path_sha256)):
            raise keys.PlantConfigError(f"path_sha256 must be 64 lower-case hex digits, got {path_sha256!r}")
        self._sha_key = path_sha256
        for key, v in (("field_name", field_name), ("field_unit", field_unit)):
            if v is not None and not isinstance(v, str):
                raise keys.PlantConfigError(f"{key} must be a string, got {v!r}")
        if field_name is not None and not field_name.isidentifier():
            raise keys.PlantConfigError(f"field_name must be an identifier (it names a PointCloud2 channel), "
                                        f"got {field_name!r}")

    def _error(self, problems: Sequence[str]) -> FMUError:
        return FMUError(f"FMU {self.path} cannot be used as a plant:\n  - " + "\n  - ".join(problems))

    def _read(self) -> Description:
        problems = archive.archive_problems(Path(self.path))
        if problems:
            raise self._error(problems)
        self.path_sha256 = archive.sha256_file(self.path)
        if self._sha_key is not None and self._sha_key != self.path_sha256:
            raise self._error([f"its SHA-256 is {self.path_sha256}, but {self._sha_key} was expected: this is "
                               "another FMU than the one the scenario or design was made with"])
        try:
            return describe(Path(self.path))
        except ImportError:
            raise self._error([FMPY_HINT]) from None
        except ValueError as exc:
            raise self._error([str(exc)]) from None

    # ------------------------------------------------------------------ resolution
    def _resolve(self, desc: Description, dt, start_time, field_name, field_unit) -> None:
        """Interface, variables and numbers from the keys and the model description; every
        problem found is raised at once."""
        self.interface = desc.choose_interface(self._interface_key)
        if self.interface is not None:
            desc.check_interface(self.interface)
        me = self.interface == "model_exchange"
        if self._substeps_key is not None and self.interface == "co_simulation":
            desc.problems.append("substeps applies to Model Exchange only (a Co-Simulation FMU integrates itself)")
        self.substeps = (self._substeps_key or 1) if me else None
        if desc.problems:
            raise self._error(desc.problems)
        noise = desc.select("noise_inputs", self._noise_key, causality=("input",), scalar=True) \
            if self._noise_key else None
        inputs = self._inputs_key or desc.default_inputs(exclude=self._noise_key or ())
        outputs = self._outputs_key or desc.default_outputs()
        for key, names in (("inputs", inputs), ("outputs", outputs)):
            if not names:
                desc.problems.append(f"{key}: the FMU declares no Real scalar {key[:-1]} variables; name them")
        if set(inputs) & set(self._noise_key or ()):
            desc.problems.append(f"inputs and noise_inputs share {sorted(set(inputs) & set(self._noise_key))}")
        self._in = desc.select("inputs", inputs, causality=("input",), scalar=True) if inputs else None
        self._out = desc.select("outputs", outputs, scalar=True) if outputs else None
        self._states = desc.state_selection() if me else None
        field = self._field_key if self._field_key is not None else (None if me else outputs)
        self._field = self._states if field is None else desc.select("field", field)
        self._noise = noise
        self._start_pairs = desc.check_start_values(self.start_values)
        if self._out is not None and self._in is not None:
            desc.check_feedthrough(self._out, list(self._in.refs) + list(noise.refs if noise else ()))
        for driven in (self._in, noise):
            if me and driven is not None:
                desc.check_multiple_set(driven)
        self.dt = self._number(desc, "dt", dt, desc.default_experiment("stepSize"), positive=True)
        self.start_time = self._number(desc, "start_time", start_time, desc.default_experiment("startTime") or 0.0)
        if desc.problems:
            raise self._error(desc.problems)
        self._describe(desc, field, field_name, field_unit)

    def _number(self, desc: Description, key: str, value, default, positive: bool = False) -> float:
        if value is None and default is None:
            desc.problems.append(f"{key}: give the plant step [s] (the FMU's DefaultExperiment has no stepSize)")
            return 1.0
        try:
            return keys.positive(key, value if value is not None else default) if positive else \
                keys.number(key, value if value is not None else default)
        except keys.PlantConfigError as exc:
            desc.problems.append(str(exc))
            return 1.0

    def _describe(self, desc: Description, field, field_name, field_unit) -> None:
        """The protocol's description attributes."""
        self.input_names = tuple(self._in.names)
        self.output_names = tuple(self._out.names)
        self.noise_inputs = None if self._noise is None else list(self._noise.names)
        self.n_u, self.n_y, self.n_field = len(self.input_names), len(self.output_names), self._field.n
        self.noise_on_inputs = self._noise is None
        self.n_w = self.n_u if self._noise is None else self._noise.n
        self.state_is_opaque = self.interface == "co_simulation"
        base = field if isinstance(field, str) else None
        self.field_name = field_name or (base if base and base.isidentifier() else "value")
        first = desc.by_name.get(self._field.names[0]) or desc.by_name.get(base or "")
        if first is None:
            first = next(v for v in desc.md.modelVariables if v.valueReference == self._field.refs[0])
        self.field_unit = field_unit if field_unit is not None else desc.unit_of(first)
        self.field_spec = field
        self.grid_shape = layout.grid_shape_of(self._grid_key, self.n_field)
        if self.grid_shape is None and self._field.shape is not None and len(self._field.shape) <= 3:
            self.grid_shape = tuple(self._field.shape)
        self._coords = layout.coordinates(self._field_coordinates_key, self.n_field, self.grid_shape)
        self._md = desc.md
        if self.state_is_opaque:
            self.field_is_state = False
            self._field_index = self._out_index = None
        else:
            where = {e: k for k, e in enumerate(self._states.elements)}
            self._field_index = _index(self._field, where)
            self._out_index = _index(self._out, where)
            self.field_is_state = self._field_index is not None and \
                np.array_equal(self._field_index, np.arange(len(where)))

    # ------------------------------------------------------------------ the instance
    def _open(self) -> None:
        """Unpack (once per content), instantiate and initialize; the steppers and x0."""
        try:
            attrs = self._md.modelExchange if self.interface == "model_exchange" else self._md.coSimulation
            member = platform_binary(int(str(self._md.fmiVersion).split(".")[0]), attrs.modelIdentifier)
            folder = archive.unpacked(Path(self.path), self.path_sha256, required=(member,))
            binding = open_instance(folder, self._md, self.interface, self._start_pairs, self.start_time, self.path)
        except ImportError:
            raise self._error([FMPY_HINT]) from None
        except (OSError, FMICallError) as exc:
            raise self._error([str(exc).replace(f"FMU {self.path}: ", "")]) from None
        self._binding, self._pid = binding, os.getpid()
        in_refs = list(self._in.refs) + (list(self._noise.refs) if self._noise else [])
        if self.interface == "model_exchange":
            self.n_x = self._states.n
            # fmpy reads FMI 2.0's completedIntegratorStepNotNeeded into this flag too
            needs = bool(getattr(self._md.modelExchange, "needsCompletedIntegratorStep", False))
            self._stepper = ExchangeStepper(binding, self.n_x, in_refs, self.dt, self.substeps, needs)
            states = ()
        else:
            reads = list(self._out.refs) + list(self._field.refs)
            self._stepper = CoSimStepper(binding, in_refs, reads, self.n_y + self.n_field, self.dt)
            states = self._stepper.fmu_states
        # the instance and its FMU states are freed when the plant goes (or on close())
        self._finalizer = weakref.finalize(self, binding.close, states)
        try:
            if self.interface == "model_exchange":
                self._x0 = binding.continuous_states(self.n_x)[None, :]
            else:
                self._x0 = self._stepper.initial_row(self.start_time)
                self.n_x = self._stepper.n_x
        except FMICallError as exc:
            raise self._error([str(exc).replace(f"FMU {self.path}: ", "")]) from None
        if not np.all(np.isfinite(self._x0)):
            raise self._error(["its initial state is not finite"])

    def _ready(self) -> None:
        """A process that inherited this plant by fork, or a closed plant, opens an instance."""
        if self._pid != os.getpid() or not self._finalizer.alive:
            self._open()

    def close(self) -> None:
        """Free the FMU instance now (it is freed when the plant is garbage-collected anyway; a
        closed plant opens a new one when it is used again)."""
        self._finalizer()

    # ------------------------------------------------------------------ protocol
    def config(self) -> dict[str, Any]:
        """The plant's keys, complete (path absolute, the FMU's SHA-256 in path_sha256)."""
        return {"path": self.path, "path_sha256": self.path_sha256, "interface": self.interface, "dt": self.dt,
                "inputs": list(self.input_names), "outputs": list(self.output_names),
                "field": self.field_spec if not isinstance(self.field_spec, tuple) else list(self.field_spec),
                "field_coordinates": self._field_coordinates_key,
                "grid_shape": None if self._grid_key is None else list(self._grid_key),
                "field_name": self.field_name, "field_unit": self.field_unit,
                "start_values": dict(self.start_values), "noise_inputs": self.noise_inputs,
                "substeps": self.substeps, "start_time": self.start_time}

    def source_files(self) -> dict[str, str]:
        """The files this plant's behaviour depends on: {"fmu": absolute path}."""
        return {"fmu": self.path}

    def field_coordinates(self) -> np.ndarray:
        return self._coords.copy()

    def initial_state(self, batch: int = 1) -> np.ndarray:
        """The state right after the FMU's initialization, repeated: (batch, n_x)."""
        return np.repeat(self._x0, int(batch), axis=0)

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """x_{k+1} = f(x_k, u_k + w_k) (or w_k on noise_inputs) for every run: a new array."""
        single = np.ndim(x) == 1
        X = np.ascontiguousarray(np.atleast_2d(np.asarray(x, dtype=float)))
        U = np.atleast_2d(np.asarray(u, dtype=float))
        if X.shape[1] != self.n_x or U.shape[1] != self.n_u or U.shape[0] not in (1, X.shape[0]):
            raise ValueError(f"step: expected states (M, {self.n_x}) and inputs (M or 1, {self.n_u}), got "
                             f"{X.shape} and {U.shape}")
        if w is not None:
            W = np.atleast_2d(np.asarray(w, dtype=float))
            if W.shape[1] != self.n_w or W.shape[0] not in (1, X.shape[0]):
                raise ValueError(f"step: expected noise (M or 1, {self.n_w}), got {W.shape}")
        if self.noise_on_inputs:
            V = U if w is None else U + W
        else:
            W = np.zeros((1, self.n_w)) if w is None else W
            rows = max(U.shape[0], W.shape[0])
            V = np.hstack([np.broadcast_to(U, (rows, self.n_u)), np.broadcast_to(W, (rows, self.n_w))])
        with self._lock:
            self._ready()
            out = self._stepper.step(X, np.ascontiguousarray(V))
        return out[0] if single else out

    def observe(self, x: np.ndarray) -> np.ndarray:
        """Noise-free outputs h(x): (M, n_y)."""
        X = np.atleast_2d(np.asarray(x, dtype=float))
        if self.state_is_opaque:
            return X[:, HEADER:HEADER + self.n_y].copy()
        if self._out_index is not None:
            return X[:, self._out_index]
        with self._lock:
            self._ready()
            return self._stepper.read(X, list(self._out.refs), self.n_y)

    def field(self, x: np.ndarray) -> np.ndarray:
        """The field: (M, n_field) (the state itself when field_is_state)."""
        if self.field_is_state:
            return x
        X = np.atleast_2d(np.asarray(x, dtype=float))
        if self.state_is_opaque:
            return X[:, HEADER + self.n_y:HEADER + self.n_y + self.n_field].copy()
        if self._field_index is not None:
            return X[:, self._field_index]
        with self._lock:
            self._ready()
            return self._stepper.read(X, list(self._field.refs), self.n_field)

    # ------------------------------------------------------------------ shipping
    # How a cluster engine ships an FMU plant (sep_control.compute.engine): the plant's spec stays
    # its type and config (JSON) as for every plant; the engine also reads the files of
    # `source_files()` once, scatters their bytes to every worker (broadcast, once per engine), and
    # a worker builds the plant with `rebuild(config, {"fmu": data})`: from its own copy of the
    # file when it has one with the same SHA-256, else from the bytes, written once per machine to
    # the cache (<cache>/<sha256>.fmu, sep_plant.plants.fmu.archive) and unpacked there once.
    @classmethod
    def from_bytes(cls, data: bytes, **config: Any) -> "FMUPlant":
        """The plant of `config` built from the FMU's bytes, where its file may be absent (a
        Dask worker): the bytes go to the cache as <sha256>.fmu (written once per machine), and
        `path` is that file. With `path_sha256` in config, other bytes are refused.

        Parameters
        ----------
        data : the FMU file's bytes (`fmu_bytes()` of the plant on the client).
        **config : the plant's keys (`config()`).

        Returns
        -------
        The plant, identical to the client's but for `path`.
        """
        sha = config.get("path_sha256")
        try:
            path = archive.cached_copy(bytes(data), sha)
        except ValueError as exc:
            raise FMUError(f"FMU bytes for {config.get('path', '?')}: {exc}") from None
        return cls(**{**config, "path": str(path), "path_sha256": archive.sha256_bytes(bytes(data))})

    def fmu_bytes(self) -> bytes:
        """The FMU file's bytes (what a worker without the file needs, once)."""
        return Path(self.path).read_bytes()

    @classmethod
    def rebuild(cls, config: Mapping[str, Any], data: bytes | Mapping[str, bytes]) -> "FMUPlant":
        """The plant of `config`: from its `path` when that file has the config's SHA-256, else
        from the FMU's bytes `data` (`from_bytes`).

        Parameters
        ----------
        config : the plant's keys (`config()`).
        data : the FMU file's bytes, or {label: bytes} of `source_files()` ({"fmu": bytes}, as a
            cluster engine ships a plant's files).

        Returns
        -------
        The plant.
        """
        if isinstance(data, Mapping):
            data = data["fmu"]
        path = config.get("path")
        if path and os.path.isfile(path) and archive.sha256_file(path) == config.get("path_sha256"):
            return cls(**config)
        return cls.from_bytes(data, **config)

    def __reduce__(self):
        """A plant pickles as its configuration and the FMU's bytes (never its instance)."""
        return (_rebuild, (self.config(), self.fmu_bytes()))

    def __repr__(self) -> str:
        return f"FMUPlant({self.path!r}, interface={self.interface!r}, n_x={self.n_x})"


def _index(sel: Selection, where: dict) -> np.ndarray | None:
    """Positions in the state vector of a selection's elements (None if one is not a state)."""
    try:
        return np.array([where[e] for e in sel.elements], dtype=np.intp)
    except KeyError:
        return None


def _rebuild(config: dict, data: bytes) -> FMUPlant:
    return FMUPlant.rebuild(config, data)


__all__ = ["FMUError", "FMUPlant"]
