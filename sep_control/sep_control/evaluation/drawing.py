"""Drawing primitives shared by the Monte Carlo figures (`sep_control.evaluation.figures`) and
the bag report's (`sep_control.bags.figures`): matplotlib on the Agg backend, plotting only.

Fields are drawn as lines over the axis along which the nodes spread for 1-D plants and as heat
maps for grid plants (2-D; the middle slice along the last axis for 3-D), so every figure works
for every plant of the protocol (docs/plants.md).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from sep_plant.protocol import PlantInfo
from sep_plant.topics import image_of_field


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path) -> Path:
    """Lay out (`tight_layout`), write as PNG (110 dpi) and close `fig`."""
    fig.tight_layout()
    return save_keeping_layout(fig, path)


def save_keeping_layout(fig, path: Path) -> Path:
    """Write as PNG (110 dpi) and close `fig` without `tight_layout` (which would fight colorbars
    spanning several panels, e.g. of a constrained layout)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return path


def unit_suffix(unit: str | None) -> str:
    """' [unit]' for axis labels, '' without a unit."""
    return f" [{unit}]" if unit else ""


def is_map(info: PlantInfo | None) -> bool:
    """Whether fields of this plant are drawn as heat maps (grid plants of 2 or 3 axes)."""
    return info is not None and info.grid_shape is not None and len(info.grid_shape) >= 2


def line_coordinate(xyz: np.ndarray) -> tuple[np.ndarray, str]:
    """The coordinate to plot a 1-D field against: the axis along which the nodes spread."""
    axis = int(np.argmax(np.ptp(xyz, axis=0))) if xyz.shape[0] > 1 else 0
    return xyz[:, axis], "xyz"[axis] + " [m]"


def map_extent(xyz: np.ndarray, grid_shape: Sequence[int]) -> list[float]:
    """imshow extent [x0, x1, y0, y1] of a grid field's first two axes (rows = first axis)."""
    g = xyz.reshape(tuple(grid_shape) + (3,))
    first = g[(slice(None),) + (0,) * (len(grid_shape) - 1)]
    second = g[(0, slice(None)) + (0,) * (len(grid_shape) - 2)]
    return [float(second[0, 1]), float(second[-1, 1]), float(first[-1, 0]), float(first[0, 0])]


def draw_field(ax, info: PlantInfo | None, xyz: np.ndarray, values: np.ndarray, *, label: str | None = None,
               vmin: float | None = None, vmax: float | None = None, cmap: str = "inferno", **line_kw):
    """A field on `ax`: a line over x (1-D), or a heat map (grid plants; 3-D: middle slice).
    Returns the image for a map (for a colorbar), else None."""
    if is_map(info):
        img = image_of_field(values, info.grid_shape)
        im = ax.imshow(img, origin="upper", extent=map_extent(xyz, info.grid_shape), vmin=vmin, vmax=vmax,
                       cmap=cmap, aspect="equal")
        ax.set(xlabel="y [m]", ylabel="x [m]")
        if len(info.grid_shape) == 3:
            ax.set_title((ax.get_title() + " " if ax.get_title() else "") + "(middle z slice)", fontsize=9)
        return im
    x, xl = line_coordinate(xyz)
    order = np.argsort(x, kind="stable")
    ax.plot(x[order], np.asarray(values)[order], label=label, **line_kw)
    ax.set_xlabel(xl)
    return None


def band_limits(target: np.ndarray, band: float) -> tuple[float, float]:
    """Colour limits of a field map: [min f* - band, max f* + band]."""
    return float(np.min(target) - band), float(np.max(target) + band)


def spread_nodes(score: np.ndarray, xyz: np.ndarray, count: int = 2, min_frac: float = 0.25,
                 exclude: Sequence[int] = ()) -> list[int]:
    """`count` nodes with the largest `score`, each at least `min_frac` of the domain's extent away
    from those already chosen (else the next best), none in `exclude`: e.g. the unsensed nodes
    where the reconstruction std is largest."""
    extent = float(np.max(np.ptp(xyz, axis=0))) or 1.0
    score = np.array(score, dtype=float)
    score[list(exclude)] = -np.inf
    chosen: list[int] = []
    for i in np.argsort(-score, kind="stable"):
        if all(np.linalg.norm(xyz[i] - xyz[j]) >= min_frac * extent for j in chosen):
            chosen.append(int(i))
        if len(chosen) == count:
            break
    for i in np.argsort(-score, kind="stable"):          # too few far apart: fill by score
        if len(chosen) == count:
            break
        if int(i) not in chosen:
            chosen.append(int(i))
    return chosen


def node_label(xyz: np.ndarray, i: int, info: PlantInfo | None) -> str:
    """'node i at (x, y) m' with as many coordinates as the plant has spatial dimensions."""
    dims = info.spatial_dims if info is not None else 1
    return "node " + str(i) + " at (" + ", ".join(f"{c:.3g}" for c in xyz[i][:max(dims, 1)]) + ") m"
