"""Impulse-response experiments on the black box: the Markov parameters TV-ERA realizes.

Markov parameters of the perturbation system around the nominal,
    Y_{k,j} = C_k A_{k-1} ... A_{j+1} B_j        (response at step k to an input impulse at j < k),
come from experiments on the plant (`impulse_experiments`): channel c at step j perturbed by
+-delta (scheme "central", the default: no O(delta) bias, two runs per impulse) or by +delta
against an unperturbed copy of the nominal in the same batch (scheme "forward": one run per
impulse, a bias of O(delta); a small delta lifts the plant's round-off into the field basis),
outputs h(x) and field f(x) recorded for lags 1..p+q. The channels are the n_u inputs and, for a
plant whose process noise does not enter through the inputs, its n_w noise channels too.

The field responses stream into an orthonormal basis Phi as they are simulated
(`sep_control.design.basis`), so only their coefficients are kept: memory n_field r + N L r n_ch,
never N L n_field n_ch. The experiments run in chunks of start steps, one task each for an
engine (`sep_control.compute.engine`), and the chunks' bases are merged in chunk order.
Only `plant.step`, `plant.observe`, `plant.field` and state snapshots are used.
Pure numpy: no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sep_plant.device import array_module_of, base_plant, step_resident, to_device, to_host_of
from sep_plant.plants.backend import namespace, to_host
from sep_plant.protocol import Plant, noise_channels, nominal_states

from sep_control.compute.budget import default_budget, runs_per_batch, worker_budget
from sep_control.compute.progress import progress
from sep_control.design.basis import IncrementalBasis
from sep_control.design.noise_sketch import NoiseSketch
from sep_control.design.runsteps import meter_of, unmetered

#: relative tolerance of the field responses' basis (against the largest response) and of its
#: final truncation to the span the field map uses (the field reconstruction needs no more; at 1e-8
#: the slab's field map has rank ~60 whatever n_x, 400 to 6400 nodes): the default of `identify`
#: and of experiment plan 0.8 (a design's plan 0.9 uses `settings.PLAN_FIELD_TOL`)
FIELD_TOL = 1e-8
#: the fewest field snapshots in one block of the basis: steps with fewer are gathered with the
#: next ones (`_FieldBlocks`, "gram" only)
MIN_FIELD_ROWS = 32
#: impulse schemes: experiments per impulse (a forward pass also steps one unperturbed copy of the
#: nominal per start step, beside its impulses, so that both sides of every difference come from
#: the same batched solve: a nominal from a separate rollout differs in round-off, which the
#: division by delta would lift into spurious field directions)
SCHEMES = {"central": 2, "forward": 1}


@dataclass
class MarkovData:
    """Markov parameters from impulse experiments around a nominal of N steps.

    Y[j, l]  = Y_{j+l, j}  (n_y, n_ch) for lags l = 1..L (index l-1), inputs j = 0..N-1;
    field Markov parameters Yf_{j+l, j} (n_field, n_ch), lags 1..Lf, kept as coefficients on an
    orthonormal basis of the field responses: Yf[j, l] = basis @ Yc[j, l] (see `sep_control.design.basis`:
    memory n_field r + N Lf r n_ch instead of N Lf n_field n_ch).
    Channels: the n_u inputs, then the noise channels (only when noise is not on the inputs), or
    r_w random combinations of them per start step when `noise` is a sketch (`noise_sketch`).
    """
    Y: np.ndarray          # (N, L, n_y, n_ch)
    Yc: np.ndarray         # (N, Lf, r, n_ch) field responses on `basis`
    basis: np.ndarray      # (n_field, r) orthonormal
    delta: float
    experiments: int
    n_u: int               # the first n_u channels are the inputs
    noise: NoiseSketch | None = None   # the noise channels' probes when sketched (`noise_sketch`)

    @property
    def Y_inputs(self) -> np.ndarray:
        return self.Y[..., :self.n_u]

    @classmethod
    def from_dense(cls, Y: np.ndarray, Yf: np.ndarray, delta: float, experiments: int, n_u: int) -> "MarkovData":
        """From dense field Markov parameters Yf (N, Lf, n_field, n_ch) (the identity basis)."""
        return cls(Y, Yf, np.eye(Yf.shape[2]), delta, experiments, n_u)

    @property
    def Yf(self) -> np.ndarray:
        """The field Markov parameters as a dense (N, Lf, n_field, n_ch) array (small grids only)."""
        return np.einsum("fr,jlrc->jlfc", self.basis, self.Yc)


def extend_nominal(U: np.ndarray, extra: int) -> np.ndarray:
    """Hold the last input for `extra` steps past N."""
    return np.vstack([U, np.repeat(U[-1:], extra, axis=0)])


def experiment_chunks(N: int, chunks: int) -> list[tuple[int, int]]:
    """The start-step ranges [j0, j1) of the experiment chunks: `chunks` near-equal ranges of
    0..N-1 (fewer when N is smaller). The chunk plan is part of the method's inputs: it fixes
    which experiments share a pass and a field basis, so it never depends on the engine."""
    if chunks < 1:
        raise ValueError(f"experiment chunks must be >= 1, got {chunks}")
    edges = np.linspace(0, N, min(chunks, max(N, 1)) + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def impulse_experiments(plant: Plant, U: np.ndarray, lags: int, field_lags: int, delta: float,
                        Xbar_ext: np.ndarray | None = None, show_progress: bool = False,
                        field_tol: float = FIELD_TOL, memory_budget: int | None = None,
                        scheme: str = "central", chunks: int = 1, engine=None,
                        U_ext: np.ndarray | None = None, noise: NoiseSketch | None = None,
                        start: int = 0, inputs_only: bool = False, stride: int = 1,
                        field_basis: str = "gram") -> MarkovData:
    """Impulse responses for every input step j < N and channel c.

    scheme "central": (y(+delta) - y(-delta)) / (2 delta), 2 N n_ch experiments; "forward":
    (y(+delta) - ybar) / delta, N n_ch experiments plus one unperturbed copy of the nominal per
    start step j, stepped in the same batch (N (n_ch + 1) runs).
    The start steps are split into `chunks` ranges (`experiment_chunks`); each chunk is one task
    for the `engine` (`sep_control.compute.engine`; in-process by default), started from its own nominal
    snapshots Xbar_ext[j0:j1]. In a chunk the experiments run as a batch in lockstep over global
    steps; experiment (j, c, +-) is active for steps j..j+lags-1 only, so a pass holds at most
    2 n_ch lags runs ((n_ch + 1) lags forward): a ring of `lags` slots, start j in slot j mod
    lags, stepped in place (no gathering of the active runs; where every slot is in an
    experiment, the step's new array becomes the ring, `_stepped`). When that batch exceeds
    `memory_budget` (`sep_control.compute.budget`), the channels are split into groups, one pass each.
    `Xbar_ext` is the nominal over N + lags steps (computed if None), `U_ext` its input (None: U,
    its last input held).
    Field responses go straight into an incremental orthonormal basis per chunk (`field_tol`
    relative to the chunk's largest response), with "gram" in blocks of at least MIN_FIELD_ROWS
    snapshots (of consecutive steps, `_FieldBlocks`); only their coefficients are kept. The chunks'
    bases are then merged in chunk order into one basis Phi: each chunk's responses phi_c C_c
    are streamed in again from their coefficients (`IncrementalBasis.merge`, blocks of 64), with
    field_tol relative to the largest response of all chunks, so the merged basis is what one
    chunk would give (the same rank to +-2), and the coefficients become C_c' T_c with
    T_c = phi_c' Phi. The result depends on the chunk plan, never on which worker finished first.
    `noise`: impulses on the sketch's r_w combinations of the noise channels instead of on each
    (`sep_control.design.noise_sketch`; start step j uses the combinations of step start + j).
    `inputs_only`: impulses on the n_u inputs only, none on the noise channels.
    `stride` > 1: impulses only at the start steps `strided_starts` (every stride-th one and the
    last), the Markov parameters of the others interpolated linearly in j at each lag
    (`interpolate_starts`): about 1/stride of the experiments, an error of O(stride^2) times
    the second difference of Y_{j+l,j} in j (the plant's time variation along the nominal). A
    sketch's noise columns are held from the start step before instead (`hold_starts`; the sketch
    must hold its combinations over the stride, `NoiseSketch.hold`).
    `field_basis`: how the basis finds new directions (`IncrementalBasis` `method`: "gram", or
    0.8.0's "svd"). `field_lags` 0: no field responses (no basis), the outputs only.
    """
    from sep_control.compute.engine import InProcess

    if scheme not in SCHEMES:
        raise ValueError(f"impulse scheme must be one of {', '.join(SCHEMES)}, got {scheme!r}")
    engine = engine or InProcess()
    N, n_u = U.shape
    # `U_ext`: the nominal input over N + lags steps when it goes on past U (a block of start
    # steps inside a longer horizon); None: U with its last input held
    U_ext = extend_nominal(U, lags) if U_ext is None else U_ext[:N + lags]
    if Xbar_ext is None:
        Xbar_ext = nominal_states(plant, U_ext)
    n_w = 0 if inputs_only or getattr(plant, "noise_on_inputs", True) else noise_channels(plant)
    if noise is not None:
        if noise.n_w != n_w:
            raise ValueError(f"a noise sketch of {noise.n_w} channels for a plant with {n_w}")
        if stride > 1 and noise.hold != stride:
            raise ValueError(f"strided impulses (stride {stride}) need a sketch held over the stride, got hold {noise.hold}")
        n_w = noise.rank
    n_ch = n_u + n_w
    n_y, n_f = int(plant.n_y), int(plant.n_field)
    in_process = engine.local
    groups = _channel_groups(plant, n_ch, lags, scheme, memory_budget, engine)
    plan = experiment_chunks(N, chunks)
    starts = strided_starts(N, stride)
    # a metered plant counts its own steps in this process; a worker steps its own copy, so its
    # experiments are counted here (every run is stepped `lags` times, `experiment_run_steps`)
    meter = None if in_process else meter_of(plant)
    shared = dict(plant=engine.ship(plant if in_process else unmetered(plant)), U_ext=U_ext, lags=lags,
                  field_lags=field_lags, delta=delta, groups=groups, n_u=n_u, n_w=n_w, scheme=scheme,
                  field_tol=field_tol, field_basis=field_basis, bar_desc="TV-ERA experiments" if (in_process and show_progress) else None,
                  n_chunks=len(plan), noise=noise, start=start)
    tasks = [(i, j0, j1, Xbar_ext[j0:j1]) if stride == 1 else
             (i, j0, j1, Xbar_ext[j0:j1], starts[(starts >= j0) & (starts < j1)] - j0) for i, (j0, j1) in enumerate(plan)]
    labels = [f"plant {type(base_plant(unmetered(plant))).__name__}: TV-ERA impulse experiments, chunk {i + 1}/{len(plan)} "
              f"(start steps {j0}..{j1 - 1}, {n_ch} channels, scheme {scheme})" for i, (j0, j1) in enumerate(plan)]
    parts = engine.map(_impulse_chunk, tasks, shared, labels, "TV-ERA experiments",
                       show_progress=show_progress and not in_process)
    if meter is not None:
        meter.add(experiment_run_steps(len(starts), n_ch, lags, scheme, len(groups)))
    Y, Yc, phi = _merge_chunks(plan, parts, (N, lags, n_y, n_ch), field_lags, n_f, field_tol, field_basis)
    if stride > 1:
        # a sketch's columns are held: each start step's own combinations (`NoiseSketch.hold`),
        # which a linear interpolation between two start steps would mix
        cut = n_u if noise is not None else n_ch
        Y, Yc = (np.concatenate([interpolate_starts(Z[..., :cut], starts), hold_starts(Z[..., cut:], starts)], axis=-1)
                 for Z in (Y, Yc))
    return MarkovData(Y, Yc, phi, delta, SCHEMES[scheme] * len(starts) * n_ch, n_u, noise)


def strided_starts(N: int, stride: int) -> np.ndarray:
    """The start steps impulsed with `stride`: 0, stride, 2 stride, ... and N - 1 (every one for 1)."""
    if stride < 1:
        raise ValueError(f"impulse stride must be >= 1, got {stride}")
    return np.union1d(np.arange(0, N, stride), [N - 1]) if N > 0 else np.zeros(0, dtype=int)


def interpolate_starts(Z: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Z (N, ...) with the rows j not in `starts` set by linear interpolation in j between the
    neighbouring start steps a <= j <= b: Z_j = (1 - w) Z_a + w Z_b, w = (j - a) / (b - a)
    (`starts` sorted, holding 0 and N - 1)."""
    j = np.arange(Z.shape[0])
    hi = starts[np.minimum(np.searchsorted(starts, j, "left"), len(starts) - 1)]
    lo = starts[np.maximum(np.searchsorted(starts, j, "right") - 1, 0)]
    w = np.where(hi > lo, (j - lo) / np.maximum(hi - lo, 1), 0.0).reshape((-1,) + (1,) * (Z.ndim - 1))
    return (1.0 - w) * Z[lo] + w * Z[hi]


def hold_starts(Z: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Z (N, ...) with the rows j not in `starts` set to the row of the start step a <= j before
    them (`starts` sorted, holding 0): a zero-order hold in j."""
    return Z[starts[np.searchsorted(starts, np.arange(Z.shape[0]), "right") - 1]]


def experiment_run_steps(N: int, n_ch: int, lags: int, scheme: str = "central", groups: int = 1) -> int:
    """Run-steps of the impulse experiments of N start steps and n_ch channels (the nominal
    rollout not included): every run is stepped `lags` times; central 2 N n_ch runs, forward
    N n_ch plus one unperturbed copy per start step and channel group."""
    runs = N * (SCHEMES[scheme] * n_ch + (groups if scheme == "forward" else 0))
    return int(runs * lags)


def _channel_groups(plant: Plant, n_ch: int, lags: int, scheme: str, memory_budget: int | None,
                    engine) -> list[np.ndarray]:
    """The channels of each lockstep pass: as many as fit `memory_budget` per start step."""
    if memory_budget is None and not engine.local:
        # the default budget is this machine's; a worker must hold a chunk's batch too (only
        # when this binds does it change the plan: pass --memory-budget for the same bits)
        wb = worker_budget(engine)
        memory_budget = None if wb is None else min(wb, default_budget())
    slot_runs = runs_per_batch(int(plant.n_x), int(plant.n_field), memory_budget) // lags   # runs per start step
    per_pass = max(1, (slot_runs - (scheme == "forward")) // SCHEMES[scheme])     # channels per pass
    return [np.arange(c, min(n_ch, c + per_pass)) for c in range(0, n_ch, per_pass)]


def _merge_chunks(plan: list[tuple[int, int]], parts: list, shape: tuple[int, int, int, int], field_lags: int,
                  n_f: int, field_tol: float, field_basis: str = "gram") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chunks' (Y, phi, Yc) as one: Y of `shape` (N, lags, n_y, n_ch), the field coefficients
    on the merged basis Phi, and Phi (see `impulse_experiments`)."""
    N, n_ch = shape[0], shape[3]
    Y = np.zeros(shape)
    basis = IncrementalBasis(n_f, field_tol, xp=namespace(*(phi for _, phi, _ in parts)), method=field_basis,
                             reserve=sum(phi.shape[1] for _, phi, _ in parts))
    flat = [Yc_local.transpose(2, 0, 1, 3).reshape(phi.shape[1], -1) if phi.shape[1] else np.zeros((0, 0))
            for _, phi, Yc_local in parts]                    # (r_c, snapshots) per chunk
    # the tolerance is against the largest response of all chunks, whatever their order
    basis.scale = max((float(np.sqrt(np.einsum("ij,ij->j", m, m)).max()) for m in flat if m.size), default=0.0)
    transfers = []
    for (j0, j1), (Yp, phi, _), m in zip(plan, parts, flat):
        Y[j0:j1] = Yp
        # each chunk's responses are streamed in again as coefficients (`IncrementalBasis.merge`):
        # entering phi_c as unit vectors would keep each chunk's own small directions (rank 172
        # instead of 63 at n_x = 1600 with 4 chunks)
        transfers.append(basis.merge(phi, m))
    r = basis.rank
    Yc = np.zeros((N, field_lags, r, n_ch))
    for (j0, j1), (_, phi, Yc_local), T in zip(plan, parts, transfers):
        if phi.shape[1]:
            # phi_c on Phi, Phi' phi_c: "gram"'s merge gave it on the columns there were then (the
            # product with all of Phi took 0.9 s per identification at plate 256^2), only the
            # columns later merges added are left to project on; "svd" projects on all (0.8.0's)
            done = 0 if T is None else T.shape[0]
            later = to_host(phi.T @ basis.phi[:, done:]).T if done < r else np.zeros((0, phi.shape[1]))
            T = later if T is None else np.vstack([T, later])
            # per (j, lag) a batched BLAS product (einsum's own loop took 7x longer at Allen-Cahn's r ~ 1000)
            Yc[j0:j1] = np.matmul(T, Yc_local)
    return Y, Yc, to_host(basis.result())


def _impulse_chunk(task: tuple, plant, U_ext: np.ndarray, lags: int, field_lags: int, delta: float,
                   groups: list[np.ndarray], n_u: int, n_w: int, scheme: str, field_tol: float,
                   field_basis: str = "gram", bar_desc: str | None = None, n_chunks: int = 1, noise: NoiseSketch | None = None,
                   start: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One experiment chunk (start steps j0..j1-1, every channel group): returns its output
    Markov parameters Y (j1-j0, lags, n_y, n_ch), its field basis phi (n_f, r_c) and the field
    coefficients Yc (j1-j0, field_lags, r_c, n_ch) on it. `plant` is the plant or its
    shipped form (`engine.ship`: rebuilt once per worker process)."""
    from sep_control.compute.engine import local_plant

    i, j0, j1, Xbar = task[:4]
    local_starts = task[4] if len(task) > 4 else None     # strided: the chunk's start steps (local)
    plant = local_plant(plant)
    n_y, n_f = int(plant.n_y), int(plant.n_field)
    n_ch = n_u + n_w
    n = j1 - j0
    Y = np.zeros((n, lags, n_y, n_ch))
    snapshots = (n if local_starts is None else len(local_starts)) * n_ch * field_lags     # the rank's bound
    basis = IncrementalBasis(n_f, field_tol, xp=array_module_of(plant), method=field_basis, reserve=snapshots)
    blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []   # (j, lag, channels, coef)
    desc = None if bar_desc is None else (bar_desc if n_chunks == 1 else f"{bar_desc} {i + 1}/{n_chunks}")
    bar = progress(None, desc or "", desc is not None, total=len(groups) * (n + lags - 1))
    for chs in groups:
        _impulse_pass(plant, U_ext[j0:], Xbar, n, lags, field_lags, delta, chs, n_u, n_w, Y, basis, blocks, bar,
                      scheme, noise, start + j0, local_starts)
    if hasattr(bar, "close"):
        bar.close()
    r = basis.rank
    Yc = np.zeros((n, field_lags, r, n_ch))
    for j, lag, chs, C in blocks:
        Cr = np.zeros((C.shape[0], r))
        Cr[:, :C.shape[1]] = C
        Yc[j[:, None], lag[:, None] - 1, :, chs[None, :]] = Cr.reshape(len(j), len(chs), r)
    return Y, basis.result(), Yc


def _impulse_pass(plant: Plant, U_ext: np.ndarray, Xbar_ext: np.ndarray, N: int, lags: int, field_lags: int,
                  delta: float, chs: np.ndarray, n_u: int, n_w: int, Y: np.ndarray, basis: IncrementalBasis,
                  blocks: list, bar, scheme: str = "central", noise: NoiseSketch | None = None,
                  start: int = 0, starts: np.ndarray | None = None) -> None:
    """One lockstep pass over the channels `chs` (see `impulse_experiments`); steps and start
    steps are counted from the chunk's first start step (U_ext and Xbar_ext begin there; it is
    start step `start` of the horizon, which picks a sketch's combinations). `starts`: the
    (local) start steps of a strided pass (None: every step)."""
    if starts is not None and len(starts) == 0:
        return
    ring = _Ring(plant, chs, n_u, n_w, lags, delta, scheme, noise, start) if starts is None else \
        _StridedRing(plant, chs, n_u, n_w, lags, delta, scheme, noise, start, starts)
    fields = _FieldBlocks(plant, basis, blocks)
    for k in range(N + lags - 1 if starts is None else int(starts[-1]) + lags):
        if hasattr(bar, "update"):
            bar.update(1)
        j_slot = ring.advance(k, N, U_ext[k], Xbar_ext[k] if k < N else None)
        ring.record(k, j_slot, field_lags, Y, fields)
    fields.flush()


class _FieldBlocks:
    """The field responses of consecutive steps, gathered into blocks of at least
    `MIN_FIELD_ROWS` snapshots before they enter the basis ("gram"; "svd", 0.8.0's, takes each
    step's block as it comes). A block costs two products with the n_f x r basis, which read Phi
    whatever the block's rows b: at b = 9 they ran at 10.8 GFLOP/s, at 18 at 22.0, at 27 at 25.9,
    at 36 at 31.6 and at 54 at 36.6 (65,536 x 200, one core). Its Gram rounds cost n_f b^2 each
    and CholeskyQR2 4 n_f K^2 per pass (K: the directions it finds), so larger blocks do not pay:
    steps gathered into blocks of up to 64 rows took plate 256^2's design work outside the plant
    step from 23.2-23.6 s to 25.3 s. A step holds few rows where the memory budget splits the
    channels into groups (one group's channels per step), and while the ring fills and empties.
    The coefficients (b, r) of a block go to `blocks` step by step, as (j, lag, channels,
    coefficients)."""

    def __init__(self, plant: Plant, basis: IncrementalBasis, blocks: list):
        self.plant, self.basis, self.blocks = plant, basis, blocks
        self.xp = array_module_of(plant)
        # a fixed number, not one from the free memory: the blocks decide the basis' bits. Memory
        # beyond a step's own block: the rows held (fewer than MIN_FIELD_ROWS) and one copy of the
        # block as it is added (0.25 GB per 32 rows at 10^6 nodes)
        self.min_rows = MIN_FIELD_ROWS if basis.method == "gram" else 0
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray, object]] = []
        self.rows = 0

    def add(self, j: np.ndarray, lag: np.ndarray, chs: np.ndarray, D) -> None:
        """One step's field responses D (len(j) len(chs), n_f), this step's own memory."""
        self.pending.append((j, lag, chs, D))
        self.rows += D.shape[0]
        if self.rows >= self.min_rows:
            self.flush()

    def flush(self) -> None:
        """Enter the pending responses into the basis, as one block."""
        if not self.pending:
            return
        parts, self.pending, self.rows = self.pending, [], 0
        D = parts[0][3] if len(parts) == 1 else self.xp.concatenate([p[3] for p in parts])
        C = to_host_of(self.plant, self.basis.add(D, overwrite=True))     # D is scratch
        # a device state is checked here, once per block
        if self.xp is not np and not np.isfinite(C).all():
            raise FloatingPointError("impulse experiments on the device gave non-finite field responses")
        i = 0
        for j, lag, chs, Dp in parts:
            self.blocks.append((j, lag, chs, C[i:i + Dp.shape[0]]))
            i += Dp.shape[0]


class _Ring:
    """The runs of one pass: a ring of `lags` slots, start step j in slot j mod lags, each slot
    [+delta e_c ..., -delta e_c ...] (central) or [+delta e_c ..., 0] (forward) for c in `chs`,
    stepped in place, range by range of active slots (`_stepped`). With a noise sketch the n_w
    channels are its
    r_w combinations: the impulse on combination i at start step j is delta d_{start+j, i}."""

    def __init__(self, plant: Plant, chs: np.ndarray, n_u: int, n_w: int, lags: int, delta: float, scheme: str,
                 noise: NoiseSketch | None = None, start: int = 0):
        self.plant, self.chs, self.n_u, self.n_w, self.lags, self.delta = plant, chs, n_u, n_w, lags, delta
        self.noise, self.start = noise, start
        self.n_w_plant = n_w if noise is None else noise.n_w
        self.m, self.sides = len(chs), SCHEMES[scheme]
        E = np.eye(n_u + n_w)[chs]
        self.pert = (np.vstack([E, -E]) if self.sides == 2 else np.vstack([E, np.zeros((1, E.shape[1]))])) * delta
        self.rows = self.pert.shape[0]
        self.xp, self.step = array_module_of(plant), step_resident(plant)    # the runs stay on a device
        self.X = self.xp.empty((lags * self.rows, int(plant.n_x)))
        self.slot_start = np.full(lags, -1)              # start step j held by each slot (-1: none)

    def advance(self, k: int, N: int, u_k: np.ndarray, xbar_k: np.ndarray | None) -> np.ndarray:
        """Start experiment k (k < N) from the nominal state xbar_k and step every run still in
        an experiment by u_k (plus the new slot's impulses); returns the start step of each slot."""
        rows, n_u, n_w, X = self.rows, self.n_u, self.n_w, self.X
        s = k % self.lags
        if k < N:
            X[s * rows:(s + 1) * rows] = to_device(self.plant, xbar_k)
            self.slot_start[s] = k
        used = min(k + 1, self.lags) * rows              # ramp-up: only the slots filled so far
        j_slot = self.slot_start[:used // rows]
        Uk = np.repeat(u_k[None], used, axis=0)
        Wk = np.zeros((used, self.n_w_plant)) if n_w else None
        if k < N:
            Uk[s * rows:(s + 1) * rows] += self.pert[:, :n_u]
            if n_w:
                pw = self.pert[:, n_u:]            # a sketch's combination i: delta d_{start+k, i}
                Wk[s * rows:(s + 1) * rows] += pw if self.noise is None else \
                    pw @ self.noise.directions(self.start + k).T
            X = self.X = _stepped(X, 0, used, self.step(X[:used], Uk, Wk))
        else:   # ramp-down: step only the slots still in an experiment (one or two ring ranges)
            for a, b in _ranges(np.flatnonzero((j_slot >= 0) & (k - j_slot < self.lags))):
                r0, r1 = a * rows, b * rows
                X = self.X = _stepped(X, r0, r1, self.step(X[r0:r1], Uk[r0:r1], None if Wk is None else Wk[r0:r1]))
        return j_slot

    def record(self, k: int, j_slot: np.ndarray, field_lags: int, Y: np.ndarray, fields: _FieldBlocks) -> None:
        """Record lag k+1-j of every active experiment j (slots of finished ones are ignored):
        outputs into Y, field responses of lags <= field_lags into `fields` (the basis)."""
        plant, rows, m, chs = self.plant, self.rows, self.m, self.chs
        lag = k + 1 - j_slot
        active = (j_slot >= 0) & (lag >= 1) & (lag <= self.lags)
        if not np.any(active):
            return
        slots = np.flatnonzero(active)
        j, lag = j_slot[slots], lag[slots]
        n_y = int(plant.n_y)
        Yo = to_host_of(plant, self._per_run_range(slots, lambda X: plant.observe(X).reshape(-1, rows, n_y)))
        Y[j[:, None], lag[:, None] - 1, :, chs[None, :]] = _difference(Yo, m, self.sides, self.delta)
        keep = lag <= field_lags
        if np.any(keep):
            n_f = int(plant.n_field)
            D = self._per_run_range(slots[keep], lambda X: _difference(
                plant.field(X).reshape(-1, rows, n_f), m, self.sides, self.delta)).reshape(-1, n_f)   # (keep m, n_f)
            fields.add(j[keep], lag[keep], chs, D)

    def _per_run_range(self, slots: np.ndarray, fn):
        """fn over the runs of the (sorted) `slots`, applied to each range of consecutive slots'
        runs in place (views of the batch: gathering the runs first copied every active run's
        whole state, ~280 MB per step at plate 256^2, to read 5 sensors), results stacked along
        the first axis in slot order. fn acts run by run (a plant's observe and field do)."""
        parts = [fn(self.X[a * self.rows:b * self.rows]) for a, b in _ranges(slots)]
        return parts[0] if len(parts) == 1 else self.xp.concatenate(parts)


class _StridedRing(_Ring):
    """A `_Ring` whose experiments start only at the (local) steps `starts`: start number i in
    slot i mod n_slots, n_slots the most experiments active at once; only the slots still in an
    experiment are stepped."""

    def __init__(self, plant: Plant, chs: np.ndarray, n_u: int, n_w: int, lags: int, delta: float, scheme: str,
                 noise: NoiseSketch | None, start: int, starts: np.ndarray):
        starts = np.asarray(starts, dtype=int)
        # the most starts within any window of `lags` steps: slot i's previous experiment,
        # start i - n_slots, has then ended (start_i - start_{i - n_slots} >= lags)
        n_slots = int(np.max(np.arange(len(starts)) + 1 - np.searchsorted(starts, starts - lags + 1)))
        super().__init__(plant, chs, n_u, n_w, n_slots, delta, scheme, noise, start)
        self.lags, self.n_slots = lags, n_slots
        self.order = {int(j): i for i, j in enumerate(starts)}
        self.filled = 0

    def advance(self, k: int, N: int, u_k: np.ndarray, xbar_k: np.ndarray | None) -> np.ndarray:
        """Start the experiment of step k when k is a start step, then step every slot still in an
        experiment by u_k (plus the new slot's impulses); returns the start step of each slot."""
        rows, n_u, n_w, X = self.rows, self.n_u, self.n_w, self.X
        i = self.order.get(k)
        if i is not None:
            s = i % self.n_slots
            X[s * rows:(s + 1) * rows] = to_device(self.plant, xbar_k)
            self.slot_start[s] = k
            self.filled = min(i + 1, self.n_slots)
        used = self.filled * rows
        j_slot = self.slot_start[:self.filled]
        Uk = np.repeat(u_k[None], used, axis=0)
        Wk = np.zeros((used, self.n_w_plant)) if n_w else None
        if i is not None:
            Uk[s * rows:(s + 1) * rows] += self.pert[:, :n_u]
            if n_w:
                pw = self.pert[:, n_u:]
                Wk[s * rows:(s + 1) * rows] += pw if self.noise is None else \
                    pw @ self.noise.directions(self.start + k).T
        for a, b in _ranges(np.flatnonzero((j_slot >= 0) & (k - j_slot < self.lags))):
            r0, r1 = a * rows, b * rows
            X = self.X = _stepped(X, r0, r1, self.step(X[r0:r1], Uk[r0:r1], None if Wk is None else Wk[r0:r1]))
        return j_slot


def _ranges(idx: np.ndarray) -> list[tuple[int, int]]:
    """Sorted indices -> the [a, b) ranges of consecutive ones."""
    if idx.size == 0:
        return []
    cut = np.flatnonzero(np.diff(idx) > 1) + 1
    return [(int(g[0]), int(g[-1]) + 1) for g in np.split(idx, cut)]


def _stepped(X, r0: int, r1: int, out):
    """The batch X with its runs r0:r1 replaced by their step `out`: `out` itself where it is the
    whole batch (a step returns a new array, `sep_plant.protocol`: taking it saves copying the
    batch back, 24 ms per step for 540 runs of 65,536 nodes on one core), else X with `out` copied
    into those rows (a ring filling or emptying; plan 0.9's short strided chunks are mostly that)."""
    if (r0 == 0 and r1 == X.shape[0] and type(out) is type(X) and out.shape == X.shape and out.dtype == X.dtype
            and out.flags.c_contiguous and getattr(out.flags, "writeable", True)):
        return out
    X[r0:r1] = out
    return X


def _difference(V: np.ndarray, m: int, sides: int, delta: float) -> np.ndarray:
    """(experiments, m, n) impulse responses from the runs V (experiments, rows, n) of one slot:
    central (V[:m] - V[m:2m]) / 2 delta, forward (V[:m] - V[m]) / delta."""
    if sides == 2:
        return (V[:, :m] - V[:, m:]) / (2 * delta)
    return (V[:, :m] - V[:, m:m + 1]) / delta
