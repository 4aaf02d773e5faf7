"""sep_estimator: part of sep (data-driven LQG control of a heat slab)."""
