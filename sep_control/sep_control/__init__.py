"""sep_control: part of sep (separation-based, data-driven LQG for large partially observed systems): design, controllers, analysis."""

__version__ = "0.7.0"
