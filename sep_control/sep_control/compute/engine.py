"""Where batches of independent runs execute: in this process, or on a Dask cluster.

Impulse experiments (by chunk of start steps), Monte Carlo runs (by chunk of run indices),
ROM-order sweep points and scenario batches are independent tasks. An engine maps one task
function over a list of chunks and returns the results *in chunk order*:

    results = engine.map(fn, chunks, shared={...}, labels=[...], desc="TV-ERA experiments")
    # == [fn(c, **shared) for c in chunks]

`InProcess` (the default) runs them here, one after another. `DaskEngine` submits them to a
dask.distributed cluster: the `shared` values (nominal snapshots, the design: the large arrays)
are scattered to the workers once per map, not sent with every task; each task's result comes
back as it finishes (the progress bar follows the futures) and the caller combines them in chunk
order, so a result never depends on which worker finished first. The TV-ERA experiments' chunks
are decided from the problem, the chunk count and the memory budget, never from the cluster: the
same chunks, combined in the same order, give the same numbers on any engine. Monte Carlo chunks
follow the workers (two per worker), which is safe because each run is computed row by row:
chunkings agree to BLAS round-off (about 1e-15 measured).

Workers rebuild the plant from plain data (`engine.ship(plant)`: the plant type and its
configuration, as in a scenario file) and keep it per process (`local_plant`), so the plant
object itself is not shipped. A plant that reads files (`source_files()`, e.g. an FMU) also has
their bytes shipped, once per engine and worker (broadcast, keyed by their SHA-256), and a worker
builds it with the class's ``rebuild(config, {label: bytes})`` (`FMUPlant.rebuild`: from its
own copy of the file when it has one with that SHA-256, else from the bytes), so no worker needs
a shared disk. A worker that dies mid-batch has its tasks rerun elsewhere by the scheduler; a task
that raises fails the map at once with a `TaskError` naming the task (the plant and the
experiments), and the remaining tasks are cancelled.

Pure Python (dask imported only when a cluster is asked for): no ROS import.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import uuid
from pathlib import Path
from typing import Any, Callable, NamedTuple, Sequence

#: seconds to wait for a scheduler given as tcp://HOST:PORT before giving up
CONNECT_TIMEOUT_S = 10.0
#: submissions of one task whose inputs were lost with their workers, before the map fails
MAX_ATTEMPTS = 3


class EngineError(RuntimeError):
    """The requested engine cannot be used (bad --dask value, scheduler unreachable)."""


class TaskError(RuntimeError):
    """A task failed; the message names the task and carries the worker's error."""


# ----------------------------------------------------------------------------- plants on workers
class PlantSpec(NamedTuple):
    """Plain data that rebuilds a plant on a worker (`plant_spec`)."""

    type_name: str                           # the plant's type string
    config: str                              # its configuration as JSON
    device: str                              # where it steps (`sep_plant.device`)
    files: tuple[tuple[str, str], ...] = ()  # (label, SHA-256) of each file of its source_files()


#: on a worker: the bytes of the plant files shipped to it, by SHA-256 (`_apply` fills it)
_WORKER_FILES: dict[str, bytes] = {}


def plant_files(plant: Any, cache: dict | None = None) -> dict[str, tuple[str, bytes]]:
    """{label: (SHA-256, bytes)} of the files of the plant's optional `source_files()`; with
    `cache` ({(path, mtime, size): (SHA-256, bytes)}), a file unchanged since is not read again."""
    from sep_plant.device import base_plant

    files = getattr(base_plant(plant), "source_files", None)
    out = {}
    for label, path in sorted(dict(files() if files is not None else {}).items()):
        st = os.stat(path)
        key = (str(path), st.st_mtime_ns, st.st_size)
        found = cache.get(key) if cache is not None else None
        if found is None:
            data = Path(path).read_bytes()
            found = (hashlib.sha256(data).hexdigest(), data)
            if cache is not None:
                cache[key] = found
        out[str(label)] = found
    return out


def plant_spec(plant: Any, files: dict[str, tuple[str, bytes]] | None = None) -> PlantSpec:
    """Plain data that rebuilds `plant` on a worker: type name, configuration as JSON, device
    (the plant part of a scenario and where it steps: a worker of a `--device cuda` run steps
    on its own GPU) and the SHA-256 of each of its files (`plant_files`, read when not given)."""
    from sep_plant.device import DevicePlant
    from sep_plant.plants import type_name_of
    from sep_plant.scenario import plain_config

    device = plant.device if isinstance(plant, DevicePlant) else "cpu"
    files = plant_files(plant) if files is None else files
    return PlantSpec(type_name_of(plant), json.dumps(plain_config(plant.config()), sort_keys=True), device,
                     tuple((label, sha) for label, (sha, _) in files.items()))


@functools.lru_cache(maxsize=8)
def worker_plant(spec: PlantSpec) -> Any:
    """The plant of `spec`, built once per process (construction may factor matrices); a plant
    with files by its class's ``rebuild(config, {label: bytes})`` from the shipped bytes."""
    from sep_plant.device import on_device
    from sep_plant.plants import make_plant, resolve

    spec = PlantSpec(*spec)
    config = json.loads(spec.config)
    rebuild = getattr(resolve(spec.type_name), "rebuild", None) if spec.files else None
    if rebuild is None:          # no files, or a class that reads them from its paths
        return on_device(make_plant(spec.type_name, config), spec.device)
    missing = [label for label, sha in spec.files if sha not in _WORKER_FILES]
    if missing:
        raise RuntimeError(f"plant {spec.type_name!r}: the bytes of its file(s) {missing} were not shipped to "
                           "this process (the engine ships them with the tasks)")
    data = {label: _WORKER_FILES[sha] for label, sha in spec.files}
    return on_device(rebuild(config, data), spec.device)


def local_plant(plant: Any) -> Any:
    """Inside a task: the plant an engine shipped (`ship`): a spec is rebuilt, a plant is itself."""
    return worker_plant(plant) if isinstance(plant, tuple) else plant


# ----------------------------------------------------------------------------------- engines
class InProcess:
    """Run every task here, in chunk order (the default; nothing is serialized)."""

    name = "in-process"
    workers = 1
    local = True             # tasks run in this process: objects are passed as they are

    def ship(self, plant: Any) -> Any:
        """What a task receives for `plant` (`local_plant` turns it back into the plant)."""
        return plant

    def map(self, fn: Callable[..., Any], chunks: Sequence[Any], shared: dict[str, Any] | None = None,
            labels: Sequence[str] | None = None, desc: str = "tasks", show_progress: bool = False) -> list:
        from sep_control.compute.progress import progress

        shared = shared or {}
        labels = list(labels) if labels is not None else [f"{desc} {i}" for i in range(len(chunks))]
        out = []
        for chunk, label in progress(list(zip(chunks, labels)), desc, show_progress and len(chunks) > 1):
            try:
                out.append(fn(chunk, **shared))
            except TaskError:
                raise
            except Exception as exc:  # noqa: BLE001 - re-raised with the task's name
                raise TaskError(f"{label}: {type(exc).__name__}: {exc}") from exc
        return out

    def memory_limit(self) -> int | None:
        return None

    def describe(self) -> str:
        return "in-process"

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class DaskEngine(InProcess):
    """Run the tasks on a dask.distributed cluster (a `Client`; a LocalCluster we own, if any)."""

    name = "dask"
    local = False

    def ship(self, plant: Any) -> PlantSpec:
        """The plant's `PlantSpec`; the bytes of its files are scattered to every worker the first
        time this engine sees them (by SHA-256) and go with every later task by reference."""
        files = plant_files(plant, self._read)
        self._file_bytes.update(files.values())
        self._scatter_files()
        return plant_spec(plant, files)

    def __init__(self, client, cluster=None):
        self.client, self.cluster = client, cluster
        self._n = 0
        self._files: dict[str, Any] = {}      # SHA-256 -> future of a plant file's bytes (on every worker)
        self._file_bytes: dict[str, bytes] = {}   # the same bytes here (to scatter again if lost)
        self._read: dict = {}                 # plant files read here (`plant_files`' cache)
        self.files_scattered = 0              # how many times plant file bytes were scattered

    @property
    def workers(self) -> int:
        return max(1, len(self.client.scheduler_info().get("workers", {})))

    def map(self, fn, chunks, shared=None, labels=None, desc="tasks", show_progress=False) -> list:
        from distributed import as_completed

        from sep_control.compute.progress import progress

        shared = shared or {}
        labels = list(labels) if labels is not None else [f"{desc} {i}" for i in range(len(chunks))]
        self._n += 1
        # scattered once; every task gets a reference (broadcast: no worker fetches from another)
        sfut = self._scatter(shared)
        tag = re.sub(r"[^A-Za-z0-9]+", "-", desc).strip("-").lower() or "task"
        # keys unique across clients: two runs sharing one scheduler must never share results
        run = uuid.uuid4().hex[:12]

        def submit(i: int, attempt: int):
            return self.client.submit(_apply, fn, chunks[i], sfut, dict(self._files),
                                      key=f"sep-{tag}-{run}-{self._n}-{i}-{attempt}", pure=False, retries=0)

        futures = [submit(i, 1) for i in range(len(chunks))]
        index = {f.key: i for i, f in enumerate(futures)}
        attempts = [1] * len(futures)
        results: list[Any] = [None] * len(futures)
        bar = progress(None, desc, show_progress, total=len(futures))
        pending = as_completed(futures)
        try:
            for fut in pending:
                i = index[fut.key]
                if fut.status == "error":
                    exc = fut.exception()
                    raise TaskError(f"{labels[i]} (on the cluster): {type(exc).__name__}: {exc}") from exc
                if fut.status != "finished":
                    # cancelled or lost: every worker holding its inputs died (the scheduler reruns
                    # tasks of a lost worker itself, but cannot recover scattered data): scatter
                    # again what was lost and resubmit, a bounded number of times
                    if attempts[i] >= MAX_ATTEMPTS:
                        raise TaskError(f"{labels[i]} (on the cluster): the task was {fut.status} "
                                        f"{attempts[i]} times (workers lost, or the cluster shut down)")
                    attempts[i] += 1
                    sfut = self._scatter(shared, sfut)
                    self._scatter_files()
                    futures[i] = submit(i, attempts[i])
                    index[futures[i].key] = i
                    pending.add(futures[i])
                    continue
                results[i] = fut.result()
                fut.release()
                if hasattr(bar, "update"):
                    bar.update(1)
        except BaseException:
            self.client.cancel(futures)
            raise
        finally:
            if hasattr(bar, "close"):
                bar.close()
            for f in sfut.values():
                f.release()
        return results

    def _scatter_files(self) -> None:
        """Scatter the plant files that no worker holds (new ones, or those whose every holder was
        lost), from their bytes here."""
        new = self._scatter(self._file_bytes, self._files)
        self.files_scattered += sum(new[sha] is not self._files.get(sha) for sha in new)
        self._files = new

    def _scatter(self, shared: dict[str, Any], old: dict | None = None) -> dict:
        """Futures of the shared values on every worker; with `old`, only those no longer held
        (in a one-element list: scatter would split a tuple or dict into several futures)."""
        out = dict(old or {})
        for k, v in shared.items():
            if k not in out or out[k].status != "finished":
                out[k] = self.client.scatter([v], broadcast=True, hash=False)[0]
        return out

    def memory_limit(self) -> int | None:
        """The smallest worker memory limit in bytes (None when unlimited or unknown)."""
        limits = [w.get("memory_limit") or 0 for w in self.client.scheduler_info().get("workers", {}).values()]
        limits = [m for m in limits if m > 0]
        return min(limits) if limits else None

    def describe(self) -> str:
        where = "LocalCluster" if self.cluster is not None else f"scheduler {self.client.scheduler.address}"
        return f"dask ({where}, {self.workers} workers; dashboard {self.client.dashboard_link})"

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            if self.cluster is not None:
                self.cluster.close()


def _apply(fn: Callable[..., Any], chunk: Any, shared: dict[str, Any], files: dict[str, bytes] | None = None) -> Any:
    """fn(chunk, **shared) on a worker (the shared values arrive as one argument, so none of their
    names can collide with `Client.submit`'s own keywords); `files`: the plant files' bytes by
    SHA-256, for `worker_plant` (references to the worker's one copy)."""
    if files:
        _WORKER_FILES.update(files)
    return fn(chunk, **shared)


def parse_dask(text: str | None) -> tuple[str, int | None] | None:
    """'local' | 'local:N' | 'tcp://HOST:PORT' (or tls://) -> ('local', N or None) / ('address', None)."""
    if text is None or text == "":
        return None
    t = text.strip()
    m = re.fullmatch(r"local(?::(\d+))?", t)
    if m:
        n = int(m.group(1)) if m.group(1) else None
        if n is not None and n < 1:
            raise EngineError(f"--dask local:N needs N >= 1, got {text!r}")
        return ("local", n)
    if re.fullmatch(r"(tcp|tls)://[^\s:/]+:\d+", t):
        return (t, None)
    raise EngineError(f"--dask must be local, local:N (N workers) or tcp://HOST:PORT of a running "
                      f"scheduler, got {text!r}")


def open_engine(text: str | None, log: Callable[[str], None] | None = None,
                connect_timeout_s: float = CONNECT_TIMEOUT_S) -> InProcess:
    """The engine for a --dask value: None -> InProcess; 'local[:N]' -> a LocalCluster of N worker
    processes with one thread each (N = the cores by default); 'tcp://HOST:PORT' -> that
    scheduler (EngineError if it does not answer within `connect_timeout_s`)."""
    spec = parse_dask(text)
    if spec is None:
        return InProcess()
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:   # pragma: no cover - dask is in requirements.txt
        raise EngineError(f"--dask needs dask.distributed ({exc}); pip install 'dask[distributed]'") from None
    where, n = spec
    if where == "local":
        n = n or os.cpu_count() or 1
        # worker processes are spawned (multiprocessing hands them this process's sys.path)
        with dask.config.set({"distributed.worker.daemon": False, "distributed.logging.distributed": "error"}):
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0",
                                   silence_logs=40)
            client = Client(cluster)
        eng = DaskEngine(client, cluster)
    else:
        try:
            client = Client(where, timeout=f"{connect_timeout_s}s")
        except (OSError, TimeoutError) as exc:
            raise EngineError(f"cannot reach the Dask scheduler at {where} within {connect_timeout_s:g} s "
                              f"({type(exc).__name__}: {exc}); start one with `dask scheduler` and "
                              f"`dask worker {where}`, or use --dask local") from None
        try:
            client.wait_for_workers(1, timeout=connect_timeout_s)
        except (OSError, TimeoutError) as exc:
            client.close()
            raise EngineError(f"the Dask scheduler at {where} has no workers after {connect_timeout_s:g} s; "
                              f"start some with `dask worker {where} --nthreads 1`") from exc
        eng = DaskEngine(client)
    if log is not None:
        log(f"engine: {eng.describe()}")
    return eng
