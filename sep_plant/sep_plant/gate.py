"""Checks of incoming contract messages, without ROS: lengths, names, finiteness, stamps, order.

Every node gates what it receives through these functions before using it (the estimator
its measurements and inputs, the plant its commands, the LQR its state estimates). The chain of
checks of one message, stamp -> horizon -> order -> vector, is written once: `check_message`
(`check_stamp` for its first two links, when a node checks the vector apart).
A failed check gives a `Rejection` (a short category for counters and a sentence for logs);
nodes count rejections per category and report them on /diagnostics.

It lives in `sep_plant` (the package every other one depends on) because the plant gates its
commands with the same code the estimator uses for measurements.  Pure Python/numpy.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from sep_plant import topics

# Rejection categories (counter keys on /diagnostics).
NON_FINITE = 'non_finite'
WRONG_LENGTH = 'wrong_length'
UNKNOWN_NAMES = 'unknown_names'
BAD_NAMES = 'bad_names'            # missing, duplicated, or names/values length mismatch
BAD_STAMP = 'bad_stamp'            # not on the k*dt grid, negative
BEYOND_HORIZON = 'beyond_horizon'  # step outside 0..last
STALE = 'stale'                    # older than the step being processed
DUPLICATE = 'duplicate'            # a second message for a step already accepted
AHEAD = 'ahead'                    # for a step the receiver has not reached (commands)
CATEGORIES = (NON_FINITE, WRONG_LENGTH, UNKNOWN_NAMES, BAD_NAMES, BAD_STAMP, BEYOND_HORIZON,
              STALE, DUPLICATE, AHEAD)


@dataclass(frozen=True)
class Rejection:
    category: str
    detail: str

    def __str__(self) -> str:
        return f'{self.category}: {self.detail}'


def check_vector(names: Sequence[str], values: Sequence[float], expected: Sequence[str],
                 what: str = 'values') -> tuple[np.ndarray | None, Rejection | None]:
    """Validate a named vector against the expected labels.

    Returns (values in the order of `expected`, None) or (None, Rejection).  Names must be
    exactly the expected labels (any order, no duplicates); every value must be finite.
    """
    n = len(expected)
    vals = np.asarray(values, dtype=np.float64).ravel()
    if vals.shape[0] != n:
        return None, Rejection(WRONG_LENGTH, f'{what}: got {vals.shape[0]} values, expected {n}')
    names = list(names)
    if len(names) != n:
        return None, Rejection(BAD_NAMES, f'{what}: got {len(names)} names for {n} values '
                                          f'(names must be {list(expected)})')
    if names != list(expected):
        unknown = [m for m in names if m not in expected]
        if unknown:
            return None, Rejection(UNKNOWN_NAMES, f'{what}: unknown names {unknown} '
                                                  f'(expected {list(expected)})')
        if len(set(names)) != n:
            dup = sorted({m for m in names if names.count(m) > 1})
            return None, Rejection(BAD_NAMES, f'{what}: duplicated names {dup}')
        order = [names.index(e) for e in expected]
        vals = vals[order]
    if not np.all(np.isfinite(vals)):
        bad = [expected[i] for i in np.flatnonzero(~np.isfinite(vals))]
        return None, Rejection(NON_FINITE, f'{what}: non-finite value (NaN/Inf) at {bad}')
    return vals, None


def step_of_stamp(ns: int, dt_ns: int) -> tuple[int | None, Rejection | None]:
    """Step k of a stamp of `ns` nanoseconds on the grid k * dt_ns, within the contract's
    tolerance (`sep_plant.topics.STAMP_TOLERANCE`, 0.1 % of dt)."""
    k = topics.step_of_stamp(ns, dt_ns)
    if k is None:
        return None, Rejection(BAD_STAMP, f'stamp {ns * 1e-9:.9f} s is not a step of '
                                          f'dt = {dt_ns * 1e-9:g} s (tolerance '
                                          f'{topics.tolerance_ns(dt_ns) * 1e-6:g} ms)')
    return k, None


def check_step(k: int, *, expected: int, last: int, allow_ahead: bool) -> Rejection | None:
    """Order check of a message for step k.

    expected: the step the receiver is about to process; last: the step of the newest
    message accepted on this input (-1 if none); allow_ahead: whether steps after `expected`
    are acceptable (a measurement after a gap) or refused (a command for a future step).
    Steps beyond the horizon are checked by the caller with `check_horizon`.
    """
    if k == last:
        return Rejection(DUPLICATE, f'second message for step {k}')
    if k < last:
        return Rejection(STALE, f'step {k} arrived after step {last} (out of order)')
    if k < expected:
        return Rejection(STALE, f'step {k} is older than the current step {expected}')
    if k > expected and not allow_ahead:
        return Rejection(AHEAD, f'step {k} is ahead of the current step {expected}')
    return None


def check_horizon(k: int, last_step: int) -> Rejection | None:
    if not 0 <= k <= last_step:
        return Rejection(BEYOND_HORIZON, f'step {k} is outside 0..{last_step}')
    return None


def check_stamp(ns: int, dt_ns: int, last_step: int) -> tuple[int | None, Rejection | None]:
    """(k, None) for a stamp of `ns` nanoseconds on the grid k * dt_ns with 0 <= k <= last_step,
    else (None, Rejection) (`step_of_stamp`, then `check_horizon`)."""
    k, rej = step_of_stamp(ns, dt_ns)
    if rej is None:
        rej = check_horizon(k, last_step)
    return (None, rej) if rej is not None else (k, None)


def check_message(ns: int, dt_ns: int, last_step: int, names: Sequence[str], values: Sequence[float],
                  expected: Sequence[str], what: str, *, order: tuple[int, int, bool] | None = None
                  ) -> tuple[int | None, np.ndarray | None, Rejection | None]:
    """The whole gate of one message: stamp on the grid -> step within 0..last_step -> order
    (when `order` = (expected step, last accepted step, allow_ahead) is given, `check_step`) ->
    named vector (`check_vector`, labelled `what`).

    Returns (k, values in the order of `expected`, None) when it passes; else (k or None, None,
    the first Rejection): k is known once the stamp passed."""
    k, rej = check_stamp(ns, dt_ns, last_step)
    if rej is None and order is not None:
        rej = check_step(k, expected=order[0], last=order[1], allow_ahead=order[2])
    if rej is not None:
        return k, None, rej
    v, rej = check_vector(names, values, expected, what)
    return k, v, rej


class RejectionLog:
    """Counts rejections per category and remembers the last one."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()
        self.last: Rejection | None = None

    def add(self, r: Rejection) -> None:
        self.counts[r.category] += 1
        self.last = r

    @property
    def total(self) -> int:
        return int(sum(self.counts.values()))

    def as_dict(self) -> dict[str, int]:
        return {c: int(self.counts[c]) for c in CATEGORIES if self.counts[c]}


def chi2_interval(dof: int, n: int, p: float = 0.95) -> tuple[float, float]:
    """Two-sided interval of the mean of n chi-square(dof) samples (normal approximation of
    the chi-square(n dof) / n), e.g. for a mean NIS; returns (lo, hi)."""
    if n <= 0:
        return 0.0, math.inf
    z = {0.95: 1.959963984540054, 0.99: 2.5758293035489004}.get(p, 1.959963984540054)
    sd = math.sqrt(2.0 * dof / n)
    return max(0.0, dof - z * sd), dof + z * sd
