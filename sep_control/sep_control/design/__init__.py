"""The offline design: nominal optimization, TV-ERA identification, LQG gains (docs/method.md).

    from sep_control.design import DesignSettings, run_design
    design = run_design(plant, problem, DesignSettings())

`run_design` and `DesignSettings` are loaded on first use, so that importing one module of this
package (e.g. `sep_control.design.gains` in a node) does not import the whole pipeline.
"""
from __future__ import annotations

from typing import Any

__all__ = ["DesignSettings", "run_design"]


def __getattr__(name: str) -> Any:
    if name == "run_design":
        from sep_control.design.pipeline import run_design
        return run_design
    if name == "DesignSettings":
        from sep_control.design.settings import DesignSettings
        return DesignSettings
    raise AttributeError(f"module 'sep_control.design' has no attribute {name!r}")
