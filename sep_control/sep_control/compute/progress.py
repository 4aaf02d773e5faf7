"""Progress bars for long offline work (tqdm on stderr; silent when disabled)."""
from __future__ import annotations

import sys
from typing import Iterable, TypeVar

T = TypeVar("T")


def progress(it: Iterable[T], desc: str, enabled: bool = True, total: int | None = None) -> Iterable[T]:
    """Wrap `it` in a tqdm bar on stderr when `enabled`, else return it unchanged."""
    if not enabled:
        return it
    from tqdm import tqdm

    return tqdm(it, desc=desc, total=total, file=sys.stderr, leave=True, dynamic_ncols=True,
                mininterval=0.2)
