"""Co-Simulation FMUs with FMU state: opaque states as fixed-length float64 rows.

A Co-Simulation FMU integrates itself (fmi2DoStep / fmi3DoStep); sep only needs to restart it
from any saved state. The state of a run is the FMU's serialized state, carried in a float64
row of fixed length n_x (the protocol's `state_is_opaque`: sep copies rows and restarts from
them, never does arithmetic on them)::

    row = [n_bytes, crc32, t, y_1 .. y_ny, f_1 .. f_nfield, payload_1 .. payload_W]

* payload: the serialized bytes, six per value, each value the little-endian integer of its six
  bytes (< 2^48: exact in float64, finite, unchanged by any copy, JSON or npz round trip);
  W = ceil(n_bytes / 6) of the FIRST serialization (the initial state). A later state larger
  than that is an error naming the sizes; a smaller one fits (n_bytes says how much is used).
* crc32 of the bytes: a row that was altered (e.g. averaged) is refused with a clear message
  before its bytes reach the FMU's deserializer.
* t: the FMU's time at this state (the next fmiDoStep starts there);
* y, f: the outputs and the field, read right after the step that made the state, so that
  observe and field are slices of the row: no FMU call, and nothing redone after a step.

One plant step, for each run m: deserialize its bytes, set the FMU state, set the inputs,
do one step of dt, read outputs and field into its row, get and serialize the new state.
Each call is checked as it returns: the first failure stops the step and is named alone.
The serialized bytes of all runs are encoded into rows in one vectorized pass.
Pure numpy/ctypes: no ROS import.
"""
from __future__ import annotations

import zlib
from collections import OrderedDict
from ctypes import byref, c_double, c_size_t, c_void_p

import numpy as np

from sep_plant.plants.fmu.binding import WARNING, Binding, FMICallError, refs_array
from sep_plant.plants.fmu.exchange import KEEP_WORKSPACES, row_pointers

#: bytes per float64 value of the payload (integers below 2^48 are exact)
BYTES_PER_VALUE = 6
#: header values before the outputs: n_bytes, crc32, t
HEADER = 3


def encode(raw: np.ndarray) -> np.ndarray:
    """Bytes (M, 6 W) uint8 -> (M, W) float64 values (each the integer of six bytes)."""
    M, nb = raw.shape
    width = nb // BYTES_PER_VALUE
    buf = np.zeros((M, width, 8), np.uint8)
    buf[:, :, :BYTES_PER_VALUE] = raw.reshape(M, width, BYTES_PER_VALUE)
    return buf.view("<u8").reshape(M, width).astype(np.float64)


def decode(values: np.ndarray) -> np.ndarray:
    """(M, W) float64 -> bytes (M, 6 W) uint8 (the inverse of `encode`)."""
    M, width = values.shape
    u = values.astype("<u8")
    return np.ascontiguousarray(u.view(np.uint8).reshape(M, width, 8)[:, :, :BYTES_PER_VALUE]).reshape(M, -1)


def _failed(b: Binding, run: int | None, call: str, status: int) -> FMICallError:
    """The error of FMI call `call` of run `run` (None: the initial state) that returned `status`.
    Each FMI call is checked right after it returns, so the first failure stops the step and is
    the one named."""
    return b.fail(f"{call} ({'initial state' if run is None else f'run {run}'})", status)


def _check(b: Binding, run: int | None, call: str, status: int) -> None:
    """Raise `_failed` when `status` is worse than a warning (the initial state's calls; the step
    inlines the same test, it runs for every run and step)."""
    if status > WARNING:
        raise _failed(b, run, call, status)


class Workspace:
    """Buffers of a batch of M runs and the prebuilt arguments of its per-run C calls (the
    byte counts and times are c_size_t / c_double objects whose values change per step)."""

    def __init__(self, st: "CoSimStepper", M: int) -> None:
        b = st.b
        cap = st.width * BYTES_PER_VALUE
        self.raw, self.new = np.zeros((M, cap), np.uint8), np.zeros((M, cap), np.uint8)
        self.V, self.reads = np.empty((M, max(st.n_in, 1))), np.empty((M, st.n_read))
        self.sizes = [c_size_t(0) for _ in range(M)]
        self.times = [c_double(0.0) for _ in range(M)]
        h_in, h_out = byref(st._in_state), byref(st._out_state)
        self.load = [(b.c, p, n, h_in) for p, n in zip(row_pointers(self.raw), self.sizes)]
        self.inputs = [b.values_args(st._in_refs, st.n_in, st.n_in, p) for p in row_pointers(self.V)]
        self.steps = [b.step_args(t, st._h) for t in self.times]
        self.outs = [b.values_args(st._read_refs, st._n_read_refs, st.n_read, p) for p in row_pointers(self.reads)]
        self.save = [(b.c, st._out_state, p, st._size) for p in row_pointers(self.new)]
        self.get_state = (b.c, h_out)
        self.free_in = (b.c, h_in)
        self.size_of = (b.c, st._out_state, byref(st._size))


class CoSimStepper:
    """Steps a Co-Simulation FMU's opaque states (see the module docstring).

    Parameters
    ----------
    binding : the initialized instance.
    input_refs : value references of the inputs set each step (columns of V).
    read_refs, n_read : the variables read after each step (outputs then field) and their count.
    dt : plant step [s].
    """

    def __init__(self, binding: Binding, input_refs: list[int], read_refs: list[int], n_read: int,
                 dt: float) -> None:
        self.b = binding
        self.n_in = len(input_refs)
        self._in_refs = refs_array(input_refs)
        self._read_refs = refs_array(read_refs)
        self._n_read_refs = len(read_refs)
        self.n_read = int(n_read)
        self.dt = float(dt)
        self._h = c_double(self.dt)
        # FMU state objects: the one deserialized into is freed as soon as it is set (FMI does not
        # promise that deserialize reuses it); the one got is reused (FMI promises that get does)
        self._in_state = c_void_p()
        self._out_state = c_void_p()
        self._size = c_size_t(0)
        self.width = 0                         # payload values per row, fixed by `initial_row`
        self._spaces: OrderedDict[int, Workspace] = OrderedDict()

    @property
    def n_x(self) -> int:
        return HEADER + self.n_read + self.width

    @property
    def fmu_states(self) -> tuple[c_void_p, c_void_p]:
        """The two FMU state objects of this stepper (to free with the instance)."""
        return self._in_state, self._out_state

    def workspace(self, M: int) -> Workspace:
        ws = self._spaces.pop(M, None) or Workspace(self, M)
        self._spaces[M] = ws
        while len(self._spaces) > KEEP_WORKSPACES:
            self._spaces.popitem(last=False)
        return ws

    # ------------------------------------------------------------------ states
    def initial_row(self, start_time: float) -> np.ndarray:
        """The row of the state right after initialization (fixes the row length)."""
        b = self.b
        row_vals = np.empty((1, self.n_read))
        _check(b, None, "get outputs", b.get_reals(*b.values_args(self._read_refs, self._n_read_refs,
                                                                  self.n_read, c_void_p(row_vals.ctypes.data))))
        _check(b, None, "get FMU state", b.get_state(b.c, byref(self._out_state)))
        _check(b, None, "get the serialized state size", b.state_size(b.c, self._out_state, byref(self._size)))
        n = int(self._size.value)
        if n < 1:
            raise FMICallError(f"FMU {b.label}: its serialized FMU state is empty")
        self.width = -(-n // BYTES_PER_VALUE)
        raw = np.zeros((1, self.width * BYTES_PER_VALUE), np.uint8)
        _check(b, None, "serialize FMU state", b.serialize(b.c, self._out_state, c_void_p(raw.ctypes.data),
                                                           self._size))
        out = np.empty((1, self.n_x))
        out[0, 0], out[0, 2] = n, start_time
        out[:, HEADER:HEADER + self.n_read] = row_vals
        out[:, HEADER + self.n_read:] = encode(raw)
        out[0, 1] = zlib.crc32(raw[0, :n].tobytes())
        return out

    def _unpack(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(bytes (M, 6 W), byte counts (M,)) of rows X, checked to be rows this plant made."""
        sizes = X[:, 0]
        payload = X[:, HEADER + self.n_read:]
        cap = self.width * BYTES_PER_VALUE
        if not (np.all(payload == np.floor(payload)) and np.all(payload >= 0) and np.all(payload < 2.0 ** 48)
                and np.all(sizes == np.floor(sizes)) and np.all((sizes >= 1) & (sizes <= cap))):
            raise ValueError(f"FMU {self.b.label}: a state row is not one this plant made (its bytes are not "
                             "whole numbers): states of a Co-Simulation FMU are opaque, copy them but do no "
                             "arithmetic on them")
        raw = decode(payload)
        for m, (n, crc) in enumerate(zip(sizes.astype(np.int64).tolist(), X[:, 1].tolist())):
            if zlib.crc32(memoryview(raw[m, :n])) != crc:
                raise ValueError(f"FMU {self.b.label}: state row {m} fails its checksum: the row was altered "
                                 "(states of a Co-Simulation FMU are opaque: copy them, do no arithmetic)")
        return raw, sizes.astype(np.int64)

    # ------------------------------------------------------------------ step
    def step(self, X: np.ndarray, V: np.ndarray) -> np.ndarray:
        """The rows after one step dt of every run: X (M, n_x), V (M, n_in) or (1, n_in)."""
        M = X.shape[0]
        raw, sizes = self._unpack(X)
        ws = self.workspace(M)
        ws.raw[...] = raw
        ws.new[...] = 0
        ws.V[...] = V
        b = self.b
        deser, set_state, free, set_v, do_step = b.deserialize, b.set_state, b.free_state, b.set_reals, b.do_step
        get_r, get_state, size_of, ser = b.get_reals, b.get_state, b.state_size, b.serialize
        h_in, size, cap = self._in_state, self._size, ws.raw.shape[1]
        status = getattr(b, "step_status", None)          # fmi3DoStep's four results (FMI 3 only)
        n_bytes, crcs = [0] * M, [0] * M
        for m, (n, t) in enumerate(zip(sizes.tolist(), X[:, 2].tolist())):
            ws.sizes[m].value, ws.times[m].value = n, t
            # one call at a time: a failed call stops the step there and is named alone (a failed
            # deserialize must never reach set-state with a bad handle, nor do-step the wrong state)
            if (st := deser(*ws.load[m])) > WARNING:
                raise _failed(b, m, "deserialize FMU state", st)
            if (st := set_state(b.c, h_in)) > WARNING:
                raise _failed(b, m, "set FMU state", st)
            if (st := free(*ws.free_in)) > WARNING:
                raise _failed(b, m, "free FMU state", st)
            if (st := set_v(*ws.inputs[m])) > WARNING:
                raise _failed(b, m, "set inputs", st)
            if (st := do_step(*ws.steps[m])) > WARNING:
                raise _failed(b, m, "do step", st)
            why = status() if status is not None else None
            if why:
                raise FMICallError(f"FMU {b.label}: do step of run {m}: {why}")
            if (st := get_r(*ws.outs[m])) > WARNING:
                raise _failed(b, m, "get outputs", st)
            if (st := get_state(*ws.get_state)) > WARNING:
                raise _failed(b, m, "get FMU state", st)
            if (st := size_of(*ws.size_of)) > WARNING:
                raise _failed(b, m, "get the serialized state size", st)
            n = size.value
            if n > cap:
                raise FMICallError(f"FMU {b.label}: its serialized state grew to {n} bytes; sep fixed the row "
                                   f"length from the initial state ({cap} bytes): states of changing size are "
                                   "not supported")
            if (st := ser(*ws.save[m])) > WARNING:
                raise _failed(b, m, "serialize FMU state", st)
            n_bytes[m], crcs[m] = n, zlib.crc32(memoryview(ws.new[m, :n]))
        out = np.empty((M, self.n_x))
        out[:, 0], out[:, 1] = n_bytes, crcs
        out[:, 2] = X[:, 2] + self.dt
        out[:, HEADER:HEADER + self.n_read] = ws.reads
        out[:, HEADER + self.n_read:] = encode(ws.new)
        return out


__all__ = ["BYTES_PER_VALUE", "CoSimStepper", "HEADER", "Workspace", "decode", "encode"]
