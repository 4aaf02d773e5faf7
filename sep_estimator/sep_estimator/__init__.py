"""sep_estimator: part of sep (separation-based, data-driven LQG for large partially observed systems): models, filters, design file."""

from sep_plant import __version__  # the one version of sep (defined in the base package)

__all__ = ["__version__"]
