"""One initialized FMU instance and fast handles to its C functions (FMI 2.0 and 3.0).

fmpy loads the shared library, instantiates and initializes (its high-level methods convert
Python lists on every call, fine for the few calls of a set-up). The per-run calls of a batched
step go through the library's C functions directly: fresh ctypes function pointers
(``dll[name]``) with no argument conversion (``argtypes`` unset), called with ctypes objects
built once per batch size (pointers into numpy rows, value-reference arrays, sizes). One such
call costs about 0.3 us, a third of what a call with ``argtypes`` conversion costs
(bench/bench_plants.py); the Model Exchange stepper makes three per run and RK4 stage.

`Fmi2` and `Fmi3` present the same small interface to the steppers (`exchange`, `cosim`):
the raw functions and the argument tuples that differ between the versions (FMI 3.0 passes
value counts and gets four results from fmi3DoStep). Pure Python: no ROS import.
"""
from __future__ import annotations

from ctypes import byref, c_bool, c_double, c_int, c_size_t, c_uint, c_void_p
from pathlib import Path
from typing import Any, Sequence

import numpy as np

#: FMI status codes above this one are failures (0 OK, 1 warning, 2 discard, 3 error, 4 fatal)
WARNING = 1


class FMICallError(RuntimeError):
    """An FMI call failed; the message names the FMU, the call and the status."""


def refs_array(refs: Sequence[int]):
    """A C array of value references."""
    return (c_uint * len(refs))(*refs)


class Binding:
    """What both FMI versions share: the fmpy object, the component and fast raw functions."""

    version = 0
    FREE_STATE = ""     # the name of fmi{2,3}FreeFMU{s,S}tate

    def __init__(self, fmu: Any, label: str, interface: str):
        self.fmu = fmu
        self.label = label
        self.interface = interface
        self.c = c_void_p(fmu.component)

    def raw(self, name: str):
        """A fresh ctypes pointer to C function `name`: no argument conversion, int result."""
        f = self.fmu.dll[name]
        f.restype = c_int
        return f

    def fail(self, what: str, status: int | None = None) -> FMICallError:
        label = {2: "discard", 3: "error", 4: "fatal"}.get(status or 0, "failure")
        return FMICallError(f"FMU {self.label}: {what} failed" + (f" (status {status}, {label})" if status else ""))

    def close(self, states: Sequence[c_void_p] = ()) -> None:
        """Free the FMU states `states` (of get/deserialize FMU state), then the instance."""
        for handle in states:
            if handle.value:
                try:
                    self.raw(self.FREE_STATE)(self.c, byref(handle))
                except Exception:  # noqa: BLE001 - best effort at exit
                    pass
        try:
            self.fmu.terminate()
        except Exception:  # noqa: BLE001 - best effort at exit
            pass
        try:
            self.fmu.freeInstance()
        except Exception:  # noqa: BLE001
            pass

    def completed_step(self) -> None:
        """fmi{2,3}CompletedIntegratorStep; FMICallError when the FMU asks for events or to stop."""
        enter, term = self.fmu.completedIntegratorStep()
        if enter or term:
            raise FMICallError(f"FMU {self.label}: fmi{self.version}CompletedIntegratorStep asks for "
                               f"{'event mode' if enter else 'termination'}: sep steps without events")

    def continuous_states(self, n: int) -> np.ndarray:
        """The FMU's continuous-state vector x (n,)."""
        x = np.empty(n)
        name = f"fmi{self.version}GetContinuousStates"
        st = self.raw(name)(self.c, c_void_p(x.ctypes.data), c_size_t(n))
        if st > WARNING:
            raise self.fail(name, st)
        return x


class Fmi2(Binding):
    version = 2
    FREE_STATE = "fmi2FreeFMUstate"

    def __init__(self, fmu: Any, label: str, interface: str):
        super().__init__(fmu, label, interface)
        self.set_reals = self.raw("fmi2SetReal")
        self.get_reals = self.raw("fmi2GetReal")
        if interface == "model_exchange":
            self.set_states = self.raw("fmi2SetContinuousStates")
            self.get_derivatives = self.raw("fmi2GetDerivatives")
        else:
            self.deserialize = self.raw("fmi2DeSerializeFMUstate")
            self.set_state = self.raw("fmi2SetFMUstate")
            self.get_state = self.raw("fmi2GetFMUstate")
            self.state_size = self.raw("fmi2SerializedFMUstateSize")
            self.serialize = self.raw("fmi2SerializeFMUstate")
            self.free_state = self.raw(self.FREE_STATE)
            self.do_step = self.raw("fmi2DoStep")
        self._false = c_int(0)

    def values_args(self, refs, n_refs: int, n_values: int, ptr: c_void_p) -> tuple:
        """Arguments of fmi2SetReal / fmi2GetReal for one buffer."""
        return (self.c, refs, c_size_t(n_refs), ptr)

    def step_args(self, t: c_double, h: c_double) -> tuple:
        """Arguments of fmi2DoStep from time t (a c_double the caller may update) by h."""
        return (self.c, t, h, self._false)


class Fmi3(Binding):
    version = 3
    FREE_STATE = "fmi3FreeFMUState"

    def __init__(self, fmu: Any, label: str, interface: str):
        super().__init__(fmu, label, interface)
        self.set_reals = self.raw("fmi3SetFloat64")
        self.get_reals = self.raw("fmi3GetFloat64")
        if interface == "model_exchange":
            self.set_states = self.raw("fmi3SetContinuousStates")
            self.get_derivatives = self.raw("fmi3GetContinuousStateDerivatives")
        else:
            self.deserialize = self.raw("fmi3DeserializeFMUState")
            self.set_state = self.raw("fmi3SetFMUState")
            self.get_state = self.raw("fmi3GetFMUState")
            self.state_size = self.raw("fmi3SerializedFMUStateSize")
            self.serialize = self.raw("fmi3SerializeFMUState")
            self.free_state = self.raw(self.FREE_STATE)
            self.do_step = self.raw("fmi3DoStep")
        self._event, self._term, self._early = c_bool(False), c_bool(False), c_bool(False)
        self._last = c_double(0.0)
        self._false = c_bool(False)

    def values_args(self, refs, n_refs: int, n_values: int, ptr: c_void_p) -> tuple:
        return (self.c, refs, c_size_t(n_refs), ptr, c_size_t(n_values))

    def step_args(self, t: c_double, h: c_double) -> tuple:
        """Arguments of fmi3DoStep from time t (a c_double the caller may update) by h."""
        return (self.c, t, h, self._false, byref(self._event), byref(self._term), byref(self._early),
                byref(self._last))

    def step_status(self) -> str | None:
        """Why the last fmi3DoStep cannot be used (None when it completed the step)."""
        if self._event.value:
            return "it asks for event handling (eventHandlingNeeded): sep steps without events"
        if self._term.value:
            return "it asks to terminate the simulation"
        if self._early.value:
            return f"it returned early at t = {self._last.value:g}"
        return None


# ------------------------------------------------------------------------------ set-up
def _set_start_values(fmu: Any, version: int, pairs: list[tuple[Any, Any]]) -> None:
    """Set parameters and start values (between instantiation and initialization)."""
    for var, value in pairs:
        vr = [var.valueReference]
        t = var.type
        if t in ("Real", "Float64"):
            (fmu.setReal if version == 2 else fmu.setFloat64)(vr, [float(value)])
        elif t == "Float32":
            fmu.setFloat32(vr, [float(value)])
        elif t in ("Integer", "Enumeration") and version == 2:
            fmu.setInteger(vr, [int(value)])
        elif t == "Boolean":
            fmu.setBoolean(vr, [bool(value)])
        elif t == "String":
            fmu.setString(vr, [str(value)])
        else:                                       # FMI 3.0 integer types: setInt32, setUInt8, ...
            getattr(fmu, "set" + ("Int64" if t == "Enumeration" else t))(vr, [int(value)])


def open_instance(unzipdir: Path, md: Any, interface: str, start_values: list[tuple[Any, Any]],
                  start_time: float, label: str) -> Binding:
    """Load, instantiate and initialize the FMU; a Model Exchange instance is left in
    continuous-time mode at `start_time`, a Co-Simulation one ready to step.

    Raises
    ------
    FMICallError naming the FMU and the call that failed.
    """
    version = int(str(md.fmiVersion).split(".")[0])
    attrs = md.modelExchange if interface == "model_exchange" else md.coSimulation
    kw = dict(guid=md.guid, unzipDirectory=str(unzipdir), modelIdentifier=attrs.modelIdentifier,
              instanceName="sep")
    step, fmu = "loading the shared library", None
    try:
        if version == 2:
            from fmpy.fmi2 import FMU2Model, FMU2Slave

            fmu = (FMU2Model if interface == "model_exchange" else FMU2Slave)(**kw)
            step = "fmi2Instantiate"
            fmu.instantiate()
            step = "setting start values"
            _set_start_values(fmu, 2, start_values)
            step = "initialization"
            fmu.setupExperiment(startTime=start_time)
            fmu.enterInitializationMode()
            fmu.exitInitializationMode()
            if interface == "model_exchange":
                _event_iteration(lambda: fmu.newDiscreteStates()[0:2], label)
                fmu.enterContinuousTimeMode()
            return Fmi2(fmu, label, interface)
        from fmpy.fmi3 import FMU3Model, FMU3Slave

        fmu = (FMU3Model if interface == "model_exchange" else FMU3Slave)(**kw)
        step = "fmi3Instantiate"
        fmu.instantiate()
        step = "setting start values"
        _set_start_values(fmu, 3, start_values)
        step = "initialization"
        fmu.enterInitializationMode(startTime=start_time)
        fmu.exitInitializationMode()
        if interface == "model_exchange":
            _event_iteration(lambda: fmu.updateDiscreteStates()[0:2], label)
            fmu.enterContinuousTimeMode()
        return Fmi3(fmu, label, interface)
    except Exception as exc:  # noqa: BLE001 - fmpy raises plain Exception / FMICallException
        _release(fmu)
        if isinstance(exc, FMICallError):
            raise
        raise FMICallError(f"FMU {label}: {step} failed: {exc}") from None


def _release(fmu: Any) -> None:
    """After a failed set-up: free the instance (and the library), or the library alone when
    there is no instance yet; best effort, the set-up's error is what the caller reports."""
    if fmu is None:
        return
    try:
        if getattr(fmu, "component", None):
            fmu.freeInstance()
        else:
            fmu.freeLibrary()
    except Exception:  # noqa: BLE001 - best effort
        pass


def _event_iteration(update, label: str, limit: int = 100) -> None:
    """Update discrete states after initialization until the FMU needs no more."""
    for _ in range(limit):
        needed, terminate = update()
        if terminate:
            raise FMICallError(f"FMU {label}: it asks to terminate right after initialization")
        if not needed:
            return
    raise FMICallError(f"FMU {label}: its event iteration after initialization did not settle in {limit} rounds")


__all__ = ["Binding", "FMICallError", "Fmi2", "Fmi3", "WARNING", "open_instance", "refs_array"]
