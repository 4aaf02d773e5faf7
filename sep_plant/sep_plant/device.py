"""Where a plant's batched steps run: `cpu` (numpy, the default) or `cuda` (CuPy on an NVIDIA GPU).

`on_device(plant, "cuda")` returns a `DevicePlant`: the same plant (every attribute and method
is the plant's own) whose `step` copies the batch to the GPU, steps it there and copies the
result back. Everything that calls `plant.step` (the TV-ERA impulse experiments, the sensitivity
experiments, the EnKF belief, the rollouts, the Monte Carlo) then runs its plant steps on the
GPU without a change, and the design's own work (POD updates, Hankel SVDs, Riccati passes) stays
on the host. What a step costs on the device is the state's round trip over the bus (16 bytes per
node-step, about 0.3-0.6 ns at 25-50 GB/s) plus the step itself; what it saves is the plant's
20-120 ns per node-step on one CPU core (docs/benchmarks.md, `bench/bench_plants.py`).

A plant may be stepped on a GPU when it says so (`device_capable = True`): its `step` must accept
arrays of any numpy-compatible module and never turn them into numpy arrays; the built-in
plants do (`sep_plant.plants.backend`). A batch goes to the device a block of up to
`DEVICE_BLOCK_NODES` nodes at a time (upload, step, download into one host array), so the GPU
holds one block's state and temporaries (about 160 bytes per node: 2.7 GB at 2^24 nodes), whatever
the batch; the CPU's blocks of 2^17 nodes would be all kernel launches there.

Pure numpy: no ROS import; CuPy is imported only for `cuda`.
"""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, fields as dc_fields
from typing import Any

import numpy as np

from sep_plant.plants.backend import namespace, to_host
from sep_plant.plants.blocks import step_in_blocks
from sep_plant.wrapping import PlantWrapper

DEVICES = ("cpu", "cuda")

#: nodes (runs x n_x) per block on a GPU: 2^24 float64 = 128 MB per state-sized temporary
DEVICE_BLOCK_NODES = 1 << 24

CUPY_HINT = ("install CuPy for your CUDA version (pip install cupy-cuda12x, or cupy-cuda13x; "
             "https://docs.cupy.dev/en/stable/install.html)")


class DeviceError(RuntimeError):
    """The device asked for is not available, or the plant cannot run there (says what to do)."""


def array_module(device: str):
    """The array module of `device`: numpy for "cpu", cupy for "cuda" (checked to see a GPU)."""
    if device == "cpu":
        return np
    if device != "cuda":
        raise DeviceError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    try:
        import cupy
    except ImportError as exc:
        raise DeviceError(f"--device cuda needs CuPy, which is not installed ({exc}): {CUPY_HINT}") from None
    try:
        count = int(cupy.cuda.runtime.getDeviceCount())
    except Exception as exc:        # CUDARuntimeError: no driver, no device
        raise DeviceError(f"--device cuda: CuPy finds no usable CUDA device ({exc}); run on a machine "
                          "with an NVIDIA GPU and driver, or use --device cpu") from None
    if count < 1:
        raise DeviceError("--device cuda: CuPy finds no CUDA device; use --device cpu")
    return cupy


#: share of the device's free memory the resident batches may use (the rest: CuPy's memory pool
#: slack, the design's field bases and sums)
DEVICE_MEMORY_SHARE = 0.6
#: state-sized float64 rows alive per run of a resident batch: the state, the stepped state (a
#: plant's step returns a new array), the field deviation and one spare. The step's own
#: temporaries are a block's, not the batch's (the plant steps DEVICE_BLOCK_NODES at a time):
#: DEVICE_BLOCK_BYTES_PER_NODE per node of one block, set aside once
DEVICE_RUN_COPIES = 4
DEVICE_BLOCK_BYTES_PER_NODE = 160


@dataclass
class TransferStats:
    """What a `DevicePlant` moved and stepped: bytes each way, run-steps, step time (`timing`)."""

    to_device: int = 0
    to_host: int = 0
    run_steps: int = 0
    step_s: float = 0.0

    def snapshot(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dc_fields(self)}


def synchronize(xp) -> None:
    """Wait for the device's queued work (CuPy); nothing for a host module or the emulator."""
    cuda = getattr(xp, "cuda", None)
    if cuda is not None:
        cuda.Device().synchronize()


def check_finite(X) -> None:
    """Raise FloatingPointError when the device array X holds a non-finite value: one reduction
    on the device and one scalar to the host (where a numpy state is checked per line solve,
    `sep_plant.plants.adi`, a device state is checked per step or per reduced result, because
    each check is a host synchronization)."""
    if not bool(namespace(X).isfinite(X.sum())):
        raise FloatingPointError("the plant's step on the device gave non-finite values: non-finite state "
                                 "or input, or a non-positive conductivity?")


def device_memory(xp) -> int:
    """Free bytes on the current device (CuPy's `mem_info` plus what its pool holds free);
    `EMULATED_DEVICE_MEMORY` for a module without `cuda` (the tests' emulator)."""
    cuda = getattr(xp, "cuda", None)
    if cuda is None:
        return EMULATED_DEVICE_MEMORY
    free, _ = cuda.runtime.memGetInfo()
    pool = xp.get_default_memory_pool()
    return int(free) + int(pool.free_bytes())


#: what the emulated device pretends to hold (bytes)
EMULATED_DEVICE_MEMORY = 8 << 30


def device_runs_per_batch(plant: Any, n_arrays: int = DEVICE_RUN_COPIES, share: float = DEVICE_MEMORY_SHARE) -> int:
    """Runs of `plant` a resident batch may hold on its device, in float64: `share` of the free
    device memory, less one block's step temporaries (DEVICE_BLOCK_BYTES_PER_NODE per node of
    `block_nodes`), over `n_arrays` state rows per run (the memory plan, docs/gpu.md). An H200
    (~140 GB free): about 2400 runs of 10^6 states."""
    xp = getattr(plant, "xp", np)
    block = int(getattr(plant, "block_nodes", DEVICE_BLOCK_NODES)) * DEVICE_BLOCK_BYTES_PER_NODE
    per_run = 8 * n_arrays * int(plant.n_x)
    return max(1, (int(share * device_memory(xp)) - block) // per_run)


class DevicePlant(PlantWrapper):
    """A device-capable plant whose batched steps run on the array module `xp` (host arrays in
    and out; see the module docstring). Every other attribute is the wrapped plant's."""

    _OWN = ("_plant", "xp", "device", "block_nodes", "stats", "timing")

    def __init__(self, plant: Any, xp, name: str, block_nodes: int = DEVICE_BLOCK_NODES):
        if not getattr(plant, "device_capable", False):
            raise DeviceError(f"plant {type(plant).__name__} steps on the CPU only: a plant stepped on a GPU "
                              "must accept CuPy arrays in step() and declare device_capable = True "
                              "(the built-in plants do); use --device cpu")
        if int(block_nodes) < 1:
            raise ValueError(f"block_nodes must be >= 1, got {block_nodes}")
        plant = copy.copy(plant)                    # its own block size; the caller's plant is untouched
        if hasattr(plant, "block_nodes"):
            plant.block_nodes = int(block_nodes)    # a device block is stepped whole
        super().__init__(plant)
        object.__setattr__(self, "xp", xp)
        object.__setattr__(self, "device", name)
        object.__setattr__(self, "block_nodes", int(block_nodes))
        object.__setattr__(self, "stats", TransferStats())
        object.__setattr__(self, "timing", False)

    def __setattr__(self, name: str, value: Any) -> None:
        """The wrapper's own names and methods (e.g. a timing wrapper of `step`) stay here; any
        other attribute (`solver`, ...) is the plant's."""
        if name == "block_nodes" and hasattr(self._plant, "block_nodes"):
            self._plant.block_nodes = int(value)    # a device block is stepped whole
        super().__setattr__(name, value)

    def __delattr__(self, name: str) -> None:
        if name in self.__dict__:
            object.__delattr__(self, name)
        else:
            delattr(self._plant, name)

    def __reduce__(self):                           # a module does not pickle: rebuild on the device
        return (on_device, (self._plant, self.device))

    def step(self, x: np.ndarray, u: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
        """x_{k+1} = f(x_k, u_k + w_k), stepped on the device a block of runs at a time; a new
        host array (the round trip: what a caller that keeps no state on the device pays)."""
        X = np.asarray(x, dtype=float)
        single = X.ndim == 1
        X = np.atleast_2d(X)
        U = np.atleast_2d(np.asarray(u, dtype=float))
        W = None if w is None else np.atleast_2d(np.asarray(w, dtype=float))

        def upload(A, i, j):                        # inputs given once for every run stay one row
            return None if A is None else self.to_device(A if A.shape[0] == 1 else A[i:j])

        def block(Xb: np.ndarray, runs: np.ndarray) -> np.ndarray:
            i, j = int(runs[0]), int(runs[-1]) + 1
            out = self.step_resident(self.to_device(Xb), upload(U, i, j), upload(W, i, j))
            check_finite(out)
            return self.to_host(out)

        out = step_in_blocks(block, X, np.arange(X.shape[0]), self.block_nodes)
        return out[0] if single else out

    def step_resident(self, X, u, w=None):
        """One batched step of device arrays (X (M, n_x) on the device, u, w host or device):
        the new state stays on the device. Stepped whole: the caller sizes the batch
        (`device_runs_per_batch`). With `timing`, the device is synchronized after the step and
        the time counted in `stats.step_s`."""
        xp = self.xp
        u = self.to_device(u) if isinstance(u, np.ndarray) else u
        w = self.to_device(w) if isinstance(w, np.ndarray) else w
        t0 = time.perf_counter() if self.timing else 0.0
        out = self._plant.step(X, u, w)
        if self.timing:
            synchronize(xp)
            self.stats.step_s += time.perf_counter() - t0
        self.stats.run_steps += int(X.shape[0]) if X.ndim > 1 else 1
        return out

    def to_device(self, A, dtype=float):
        """A host array on the device, as `dtype` (counted in `stats`)."""
        A = np.ascontiguousarray(A, dtype=dtype)
        self.stats.to_device += A.nbytes
        return self.xp.asarray(A)

    def to_host(self, A) -> np.ndarray:
        """A device array's host copy (counted in `stats`)."""
        out = to_host(A)
        self.stats.to_host += out.nbytes
        return out

    def __repr__(self) -> str:
        return f"DevicePlant({self._plant!r}, device={self.device!r})"


def on_device(plant: Any, device: str = "cpu", xp=None) -> Any:
    """`plant` itself for "cpu"; a `DevicePlant` stepping on `device` otherwise (`xp`: the array
    module, for tests; default `array_module(device)`)."""
    if device == "cpu" and xp is None:
        return plant
    return DevicePlant(plant, array_module(device) if xp is None else xp, device)


def _device_of(plant: Any) -> "DevicePlant | None":
    """The `DevicePlant` that steps `plant`: itself, or the one a wrapper around it names as its
    `device_plant` (e.g. the design's run-step meter, which must not hide the device); None on
    the CPU."""
    if isinstance(plant, DevicePlant):
        return plant
    inner = getattr(plant, "device_plant", None)
    return inner if isinstance(inner, DevicePlant) else None


def array_module_of(plant: Any):
    """The array module a plant's resident batches live in: the `DevicePlant`'s, else numpy."""
    device = _device_of(plant)
    return np if device is None else device.xp


def step_resident(plant: Any):
    """The batched step whose state stays where it is: `step_resident` on a device (the
    wrapper's own, so that a wrapper still sees the steps), the plant's own `step` on the CPU
    (numpy in, numpy out: the host path unchanged)."""
    return plant.step if _device_of(plant) is None else plant.step_resident


def to_device(plant: Any, A, dtype=float):
    """A host array in `plant`'s array module, as `dtype` (itself on the CPU)."""
    device = _device_of(plant)
    return A if device is None else device.to_device(A, dtype)


def to_host_of(plant: Any, A) -> np.ndarray:
    """A resident array's host copy (itself on the CPU), counted in the plant's `stats`."""
    device = _device_of(plant)
    return A if device is None else device.to_host(A)


def base_plant(plant: Any) -> Any:
    """The plant a `DevicePlant` wraps (the plant itself otherwise): what is shipped and described."""
    return plant.plant if isinstance(plant, DevicePlant) else plant


__all__ = ["DEVICES", "DEVICE_BLOCK_BYTES_PER_NODE", "DEVICE_BLOCK_NODES", "DEVICE_MEMORY_SHARE", "DEVICE_RUN_COPIES", "DeviceError",
           "DevicePlant", "TransferStats", "array_module", "array_module_of", "base_plant", "check_finite",
           "device_memory", "device_runs_per_batch", "on_device", "step_resident", "synchronize", "to_device",
           "to_host_of"]
