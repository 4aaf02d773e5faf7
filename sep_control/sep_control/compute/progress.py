"""Progress bars for long offline work (tqdm on stderr; silent when disabled).

The command-line tools draw a bar only when stderr is a terminal and ``--quiet`` is not given
(`bars_wanted`): a log file or a pipe gets no carriage-return noise. Monte Carlo style work
(evaluate, validate) is counted in run-steps, one run stepped once (`RunSteps`), so that a bar
over runs of different lengths (impulse experiments of p + q steps, episodes of N steps) moves
in proportion to the plant steps taken.
"""
from __future__ import annotations

import sys
from typing import Iterable, TextIO, TypeVar

T = TypeVar("T")


def bars_wanted(quiet: bool = False, stream: TextIO | None = None) -> bool:
    """Whether a command should draw progress bars: not `quiet` and `stream` (stderr by
    default) is a terminal."""
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    return not quiet and bool(isatty and isatty())


def progress(it: Iterable[T], desc: str, enabled: bool = True, total: int | None = None) -> Iterable[T]:
    """Wrap `it` in a tqdm bar on stderr when `enabled`, else return it unchanged."""
    if not enabled:
        return it
    from tqdm import tqdm

    return tqdm(it, desc=desc, total=total, file=sys.stderr, leave=True, dynamic_ncols=True,
                mininterval=0.2)


class RunSteps:
    """A bar counted in run-steps (M runs of n steps: M n), advanced with `add`.

    Parameters
    ----------
    total : int
        Run-steps of the whole command (known beforehand from the runs and their lengths).
    desc : str
        The bar's label.
    enabled : bool
        Draw the bar (see `bars_wanted`); when False every method does nothing.
    """

    def __init__(self, total: int, desc: str, enabled: bool = True):
        self.done = 0
        self.total = int(total)
        self._bar = progress(None, desc, enabled and self.total > 0, total=self.total)

    def add(self, runs: int, steps: int = 1) -> None:
        """Count `runs` runs of `steps` steps each."""
        n = int(runs) * int(steps)
        self.done += n
        if hasattr(self._bar, "update"):
            self._bar.update(n)

    def close(self) -> None:
        if hasattr(self._bar, "close"):
            self._bar.close()

    def __enter__(self) -> "RunSteps":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
