"""sep_control: part of sep (data-driven LQG control of a heat slab)."""

__version__ = "0.1.0"
