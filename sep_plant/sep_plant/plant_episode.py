"""One plant episode without ROS: what the plant node does between its topics.

Per step k = 0..N: y_k = h(x_k) + v_k goes out (after the clock reads k dt); if k < N, the
command of step k is awaited, clipped to the input limits, then (rate limits, du_max) to within
du_max of the input applied at k-1 (`rate_clips` counts the channel-steps that clip changed),
goes out as the applied input, and x_{k+1} = f(x_k, u_k, w_k). The noise of (seed, run) is run `run` of
`sep_plant.noise.noise_sequences(problem, info, seed, runs)`, the numbers the offline Monte
Carlo uses for that run, and the episode starts from that run's initial state
(`sep_plant.initial.initial_states`), so a lockstep episode reproduces it exactly.

Modes (docs/reference/topics.md):

* lockstep: wait (up to `command_timeout_s`) for a valid command of step k; none: `CommandTimeout`.
* realtime: a tick every dt / real_time_factor on the caller's clock. A command of step k that
  has not come by the tick is a deadline miss: the last applied input is held (zeros before the
  first command: the plant does not know the nominal).

Commands pass the gate (`sep_plant.gate`): a stamp off the step grid, a step beyond the
horizon, stale, duplicate or ahead of the step the plant is at, wrong names or length, a
non-finite value: rejected and counted per reason (`rejections`), never applied.

The caller (the node) owns the clock and the transport: it passes `wait`, which runs its
message callbacks (they call `command`) until a time or until a condition holds, and a sink
that publishes what the episode produces.
Pure numpy: no ROS import.
"""
from __future__ import annotations

import time
from typing import Callable, Protocol, Sequence

import numpy as np

from sep_plant import gate, topics
from sep_plant.initial import initial_states
from sep_plant.noise import DEFAULT_SEED, noise_sequences
from sep_plant.problem import Problem
from sep_plant.protocol import Plant, PlantInfo, clip_inputs, clip_rate

MODES = ('lockstep', 'realtime')
#: the exit code of a node whose episode cannot go on (no command, no peer in time)
EXIT_TIMEOUT = 3

#: wait(t_end, done) -> done(): run the message callbacks until done() holds or the clock reads t_end
Wait = Callable[[float, Callable[[], bool]], bool]


class EpisodeError(Exception):
    """The episode cannot go on (e.g. lockstep command timeout): the node logs it and exits
    with `exit_code`."""

    def __init__(self, message: str, exit_code: int = EXIT_TIMEOUT):
        super().__init__(message)
        self.exit_code = exit_code


class CommandTimeout(EpisodeError):
    """Lockstep: no valid command of the step within command_timeout_s."""


class EpisodeSink(Protocol):
    """Where the episode's outputs go (the plant node publishes them). A sink may also have
    ``before_step(k)``, called before step k is measured: a managed plant node holds there
    while it is inactive."""

    def clock(self, k: int) -> None:
        """Step k begins: the time is k dt (published before y_k)."""

    def measurement(self, k: int, y: np.ndarray) -> None:
        """y_k (n_y,)."""

    def applied(self, k: int, u: np.ndarray) -> None:
        """The input applied at step k (n_u,), after the limits."""

    def field(self, k: int, field: Callable[[], np.ndarray]) -> None:
        """The true field of step k; `field()` computes it (only if wanted)."""

    def deadline_miss(self, k: int, period: float) -> None:
        """Realtime: no valid command of step k by its tick; the held input is applied."""


class PlantEpisode:
    """One episode of N steps of a plant.

    Parameters
    ----------
    plant : Plant
        The simulator (checked against the plant protocol by the caller).
    problem : Problem
        Horizon N, noise levels and input limits.
    seed, run : int
        The noise: run `run` of the Monte Carlo with seed `seed`.
    mode : str
        'lockstep' or 'realtime'.
    real_time_factor : float
        Realtime: a step every dt / real_time_factor (clock seconds).
    command_timeout_s : float
        Lockstep: how long to wait for each command.
    keep_trajectory : bool
        Keep F (N+1, n_field), U (N, n_u), Y (N+1, n_y) (`trajectory`).
    clock : callable
        Seconds of a steady clock (the one `wait` measures `t_end` on).

    Attributes
    ----------
    k : int
        The step the episode is at.
    rejections : gate.RejectionLog
        Rejected commands per reason.
    deadline_misses : int
        Realtime steps whose command came too late (or never).
    rate_clips : int
        Channel-steps whose command the rate limit (du_max) clipped.
    """

    def __init__(self, plant: Plant, problem: Problem, *, seed: int = DEFAULT_SEED, run: int = 0,
                 mode: str = 'lockstep', real_time_factor: float = 10.0, command_timeout_s: float = 10.0,
                 keep_trajectory: bool = False, clock: Callable[[], float] = time.perf_counter):
        if mode not in MODES:
            raise ValueError(f'mode must be one of {list(MODES)}, got {mode!r}')
        self.plant, self.problem = plant, problem
        self.info = info = PlantInfo.of(plant)
        self.mode, self.real_time_factor, self.command_timeout_s = mode, real_time_factor, command_timeout_s
        self.clock = clock
        self.N = N = problem.n_steps
        self.dt = info.dt
        self.dt_ns = topics.dt_ns(info.dt)
        self.input_names = list(info.input_names)
        w, v = noise_sequences(problem, info, seed, [run])
        self.w, self.v = w[0], v[0]
        self.seed, self.run_index = int(seed), int(run)
        self.lo, self.hi = problem.limits(info.n_u)
        self.du_max = problem.channels("du_max", info.n_u)
        self.rate_clips = 0
        self.k = 0
        self.last_cmd_step = -1
        self.pending: np.ndarray | None = None     # accepted command for step self.k
        self.held = np.zeros(info.n_u)             # last applied (zeros before the first command)
        self.rejections = gate.RejectionLog()
        self.deadline_misses = 0
        self.t_pub = np.full(N + 1, np.nan)        # clock time y_k went out
        self.t_cmd = np.full(N, np.nan)            # clock time command k arrived
        self.t_start: float | None = None
        self.F = np.empty((N + 1, info.n_field)) if keep_trajectory else None
        self.U = np.empty((N, info.n_u)) if keep_trajectory else None
        self.Y = np.empty((N + 1, info.n_y)) if keep_trajectory else None

    @property
    def period(self) -> float:
        """Realtime: clock seconds per step."""
        return self.dt / self.real_time_factor

    # ----------------------------------------------------------------- input
    def command(self, stamp_ns: int, names: Sequence[str], values: Sequence[float],
                t: float | None = None) -> gate.Rejection | None:
        """A command message (stamp in nanoseconds, input names, values) arrived at clock time t.

        Returns None when it is the command of the current step (kept for it), else the
        `gate.Rejection` (counted in `rejections`)."""
        t = self.clock() if t is None else t
        k, u, rej = gate.check_message(stamp_ns, self.dt_ns, self.N - 1, names, values, self.input_names,
                                       'command effort', order=(self.k, self.last_cmd_step, False))
        if rej is not None:
            self.rejections.add(rej)
            return rej
        self.last_cmd_step = k
        self.pending = u
        self.t_cmd[k] = t
        return None

    def has_command(self) -> bool:
        """Whether the command of the current step has come."""
        return self.pending is not None

    # ------------------------------------------------------------------- run
    def run(self, wait: Wait, sink: EpisodeSink) -> None:
        """Step the episode to its end (k = N), raising `CommandTimeout` in lockstep when a
        command does not come."""
        x = initial_states(self.plant, self.seed, [self.run_index])     # run `run`'s draw (`sep_plant.initial`)
        self.t_start = self.clock()
        before_step = getattr(sink, 'before_step', None)
        for k in range(self.N + 1):
            self.k = k
            if before_step is not None:
                before_step(k)
            self._measure(k, x, sink)
            if k == self.N:
                self._field(k, x, sink)
                break
            u = clip_inputs(self._await_command(k, wait, sink), self.lo, self.hi)
            if k > 0:
                rated = clip_rate(u, self.held, self.du_max)
                self.rate_clips += int(np.count_nonzero(rated != u))
                u = rated
            self.pending = None
            self.held = u
            if self.U is not None:
                self.U[k] = u
            sink.applied(k, u)
            self._field(k, x, sink)
            x = self.plant.step(x, u[None], self.w[k][None])
        self.k = self.N

    def _measure(self, k: int, x: np.ndarray, sink: EpisodeSink) -> None:
        y = self.plant.observe(x)[0] + self.v[k]
        if self.Y is not None:      # kept here, so that an episode cut short at step k has F[k]
            self.Y[k] = y
            self.F[k] = self.plant.field(x)[0]
        sink.clock(k)
        self.t_pub[k] = self.clock()
        sink.measurement(k, y)

    def _field(self, k: int, x: np.ndarray, sink: EpisodeSink) -> None:
        """The field of step k for the sink, after the command: the kept one, else computed only
        if the sink asks for it."""
        if self.F is not None:
            sink.field(k, lambda k=k: self.F[k])
        else:
            sink.field(k, lambda x=x: self.plant.field(x)[0])

    def _await_command(self, k: int, wait: Wait, sink: EpisodeSink) -> np.ndarray:
        """The command of step k (realtime: the held input after a deadline miss)."""
        if self.mode == 'realtime':
            wait(self.t_start + (k + 1) * self.period, lambda: False)    # the tick: steps on schedule
            if self.pending is None:
                self.deadline_misses += 1
                sink.deadline_miss(k, self.period)
                return self.held
            return self.pending
        if not wait(self.clock() + self.command_timeout_s, self.has_command):
            why = (f'; {self.rejections.total} command(s) rejected, last: {self.rejections.last}'
                   if self.rejections.total else '')
            raise CommandTimeout(f'lockstep: no valid command stamped step {k} (t = {k * self.dt:g} s) '
                                 f'within command_timeout_s = {self.command_timeout_s:g} s{why}')
        return self.pending

    # ---------------------------------------------------------------- report
    def latencies(self) -> np.ndarray:
        """Seconds from y_k going out to command k arriving, for the steps that got one."""
        d = self.t_cmd - self.t_pub[:-1]
        return d[np.isfinite(d)]

    def trajectory(self, steps: int) -> dict[str, np.ndarray]:
        """F, U, Y of the first `steps` steps (needs keep_trajectory)."""
        if self.F is None:
            raise ValueError('the trajectory was not kept (keep_trajectory=False)')
        return {'F': self.F[:steps + 1], 'U': self.U[:steps], 'Y': self.Y[:steps + 1]}
