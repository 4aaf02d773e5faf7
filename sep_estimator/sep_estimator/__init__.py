"""sep_estimator: part of sep (separation-based, data-driven LQG for large partially observed systems): models, filters, design file."""
