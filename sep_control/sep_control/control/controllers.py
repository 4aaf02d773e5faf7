"""The control laws as one kind of object, used alike by the Monte Carlo and the nodes.

A `Controller` maps step k and the filter's estimate to the input of step k:

* `OpenLoop`:  u_k = clip(ubar_k)                          (the filter still runs; its estimate is unused)
* `LqrLaw`:    u_k = clip(ubar_k + K_k zhat_{k|k})         (rom_lqg on the design's LQG, oracle_lqg on the oracle's);
               with rate limits then u_k = clip(u_k, u_{k-1} - du_max, u_{k-1} + du_max), u_{k-1}
               its own last command (a rate clip after the box clip; counted in `rate_clips`)
* `MpcLaw`:    u_k = the first move of the box-constrained ROM-MPC (`sep_control.control.mpc.RomMPC`),
               with the warm start of every run kept inside the law.

`command(k, estimate)` takes a batch of estimates (M, n_est), the Monte Carlo's runs, or one
estimate (n_est,), a node's, and returns inputs of the same leading shape, (M, n_u) or (n_u,).
The estimate is the filter's whole state z_hat: the ROM state a_hat, followed by the disturbance
estimates d_hat when the design has disturbance states (`sep_estimator.disturbance`,
n_est = n_r + n_d). The LQR and MPC laws are designed on that augmented model (`LQG.model`) and
read all n = n_est entries (K_k is (n_u, n_r + n_d): u = clip(ubar + K_a ahat + K_d dhat)); a
law reads the first `n` entries of a longer estimate (docs/method.md).

Names (`CONTROLLER_NAMES`, the same in `evaluate --controllers`, the node parameter
``controller`` and the metrics JSON): open_loop, rom_lqg, oracle_lqg, rom_mpc. The nodes' old
values ``lqr`` and ``mpc`` are `CONTROLLER_ALIASES`.
Pure numpy (+ osqp for the MPC): no ROS import.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from sep_estimator.ltv import LQG
from sep_plant.problem import Problem
from sep_plant.protocol import clip_inputs, clip_rate

from sep_control.control.mpc import DEFAULT_HORIZON, MPCStats
from sep_control.design.gains import command as lqr_command

CONTROLLER_NAMES = ("open_loop", "rom_lqg", "oracle_lqg", "rom_mpc")
#: controllers a node can run (the oracle needs the full-order model, the open loop no node)
NODE_CONTROLLERS = ("rom_lqg", "rom_mpc")
#: old names still accepted (with a deprecation message) -> their names now
CONTROLLER_ALIASES = {"lqr": "rom_lqg", "mpc": "rom_mpc"}


@runtime_checkable
class Controller(Protocol):
    """A control law u_k = law_k(estimate).

    Attributes
    ----------
    name : str
        One of `CONTROLLER_NAMES`.
    n : int
        How many leading entries of the filter's estimate the law reads.
    stats : MPCStats or None
        The law's own counters (the MPC's QPs and fallbacks); None for a law without any.
    """

    name: str
    n: int
    stats: MPCStats | None

    def command(self, k: int, estimate: np.ndarray) -> np.ndarray:
        """The input of step k.

        Parameters
        ----------
        k : int
            The step, 0 <= k < N.
        estimate : ndarray, shape (M, n_est) or (n_est,)
            The filter's estimate after the measurement update of step k, ahat_{k|k}, of M runs
            or of one (n_est >= n).

        Returns
        -------
        ndarray, shape (M, n_u) or (n_u,)
            The inputs, inside the input limits.
        """
        ...


@dataclass(frozen=True)
class MpcOptions:
    """Options of the ROM-MPC (`sep_control.control.mpc.RomMPC`).

    Parameters
    ----------
    horizon : int
        Horizon H in steps (shortened to the steps left at the end of the episode).
    time_budget_s : float or None
        A QP slower than this falls back to the clipped LQR command; None (offline) never, so
        that results do not depend on the machine's load.
    solver_settings : dict or None
        OSQP settings over `sep_control.control.mpc.OSQP_SETTINGS`.
    """

    horizon: int = DEFAULT_HORIZON
    time_budget_s: float | None = None
    solver_settings: dict | None = field(default=None, hash=False)

    @classmethod
    def of(cls, options: "MpcOptions | dict | None") -> "MpcOptions":
        """Options from an instance, a dict of the same keys, or None (the defaults)."""
        if isinstance(options, cls):
            return options
        return cls(**(options or {}))


class OpenLoop:
    """u_k = clip(ubar_k) whatever the estimate."""

    name = "open_loop"
    stats = None

    def __init__(self, u_nom: np.ndarray, lo: np.ndarray, hi: np.ndarray, n: int):
        self.u_nom, self.lo, self.hi, self.n = u_nom, lo, hi, int(n)

    def command(self, k: int, estimate: np.ndarray) -> np.ndarray:
        shape = np.shape(estimate)[:-1] + (self.u_nom.shape[1],)
        return clip_inputs(np.broadcast_to(self.u_nom[k], shape), self.lo, self.hi)


class LqrLaw:
    """u_k = clip(ubar_k + K_k ahat_k): the TV-LQR around the nominal (`sep_control.design.gains`).

    With rate limits (`du_max` finite) the box-clipped command is then clipped to within du_max
    of the law's own command of step k-1 (kept per run between calls, like the MPC's warm
    start; none at k = 0 or after a call with another number of runs); `rate_clips` counts the
    channel-steps that clip changed."""

    stats = None

    def __init__(self, lqg: LQG, u_nom: np.ndarray, lo: np.ndarray, hi: np.ndarray, name: str = "rom_lqg",
                 du_max: np.ndarray | None = None):
        self.name, self.K, self.u_nom, self.lo, self.hi = name, lqg.K, u_nom, lo, hi
        self.n = int(lqg.K.shape[2])
        self.du_max = None if du_max is None or np.all(np.isinf(du_max)) else np.asarray(du_max, dtype=float)
        self.rate_clips = 0
        self._prev: np.ndarray | None = None

    def command(self, k: int, estimate: np.ndarray) -> np.ndarray:
        u = lqr_command(self.u_nom[k], self.K[k], estimate[..., :self.n], self.lo, self.hi)
        if self.du_max is None:
            return u
        prev = self._prev if (k > 0 and self._prev is not None and self._prev.shape == u.shape) else None
        out = clip_rate(u, prev, self.du_max)
        if prev is not None:
            self.rate_clips += int(np.count_nonzero(out != u))
        self._prev = np.array(out, dtype=float)
        return out


class MpcLaw:
    """The first move of the box-constrained ROM-MPC; each run's warm start (its previous
    solution shifted by one step) is kept here between calls.

    A call with another number of runs than the last one starts cold (no warm start). A step the
    caller does not ask for (a node's nominal fallback) leaves the warm start of the last one.
    """

    name = "rom_mpc"

    def __init__(self, lqg: LQG, problem: Problem, u_nom: np.ndarray, options: MpcOptions = MpcOptions()):
        from sep_control.control.mpc import RomMPC

        self.mpc = RomMPC(lqg, problem, u_nom, horizon=options.horizon, time_budget_s=options.time_budget_s,
                          solver_settings=options.solver_settings)
        self.n = self.mpc.n
        self.stats = self.mpc.stats
        self._warm: np.ndarray | None = None
        self._prev: np.ndarray | None = None        # each run's last input (rate limits)

    @property
    def horizon(self) -> int:
        return self.mpc.H

    def reset(self) -> None:
        """A new episode: no warm starts (the counters in `stats` go on)."""
        self._warm = None
        self._prev = None

    def command(self, k: int, estimate: np.ndarray) -> np.ndarray:
        single = np.ndim(estimate) == 1
        a = np.atleast_2d(estimate)[:, :self.n]
        warm = self._warm if self._warm is not None and self._warm.shape[0] == a.shape[0] else None
        prev = self._prev if (k > 0 and self._prev is not None and self._prev.shape[0] == a.shape[0]) else None
        U, Z = self.mpc.command_batch(k, a, warm, prev=prev)
        self._warm = self.mpc.shift(Z)
        self._prev = U.copy() if self.mpc.rated else None
        return U[0] if single else U


def make_controller(name: str, lqg: LQG, problem: Problem, u_nom: np.ndarray,
                    mpc: MpcOptions | dict | None = None) -> Controller:
    """The control law `name` around the nominal input `u_nom`.

    Parameters
    ----------
    name : str
        'open_loop', 'rom_lqg', 'oracle_lqg' or 'rom_mpc' (`CONTROLLER_NAMES`).
    lqg : LQG
        The LQG the law uses: the design's (rom_lqg, rom_mpc), the oracle's (oracle_lqg); for
        open_loop only its state dimension.
    problem : Problem
        The problem (input limits; the MPC's weights).
    u_nom : ndarray, shape (N, n_u)
        The nominal input ubar.
    mpc : MpcOptions, dict or None
        Options of rom_mpc (ignored by the other laws).

    Returns
    -------
    Controller
        A new law (an MPC keeps state between calls: one per episode or Monte Carlo chunk).
    """
    lo, hi = problem.limits(u_nom.shape[1])
    if name == "open_loop":
        return OpenLoop(u_nom, lo, hi, lqg.model.n)
    if name in ("rom_lqg", "oracle_lqg"):
        return LqrLaw(lqg, u_nom, lo, hi, name, problem.channels("du_max", u_nom.shape[1]))
    if name == "rom_mpc":
        return MpcLaw(lqg, problem, u_nom, MpcOptions.of(mpc))
    raise ValueError(f"unknown controller {name!r}: use {', '.join(CONTROLLER_NAMES)}")


def resolve_controller_name(value: str, allowed: tuple[str, ...] = CONTROLLER_NAMES) -> tuple[str, str | None]:
    """(the controller's name, the deprecated spelling that was used or None) for a user's value.

    Raises ValueError naming the allowed values."""
    name = CONTROLLER_ALIASES.get(value, value)
    if name not in allowed:
        raise ValueError(f"must be {' or '.join(repr(a) for a in allowed)}, got {value!r}")
    return name, (value if value != name else None)
