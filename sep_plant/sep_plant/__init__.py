"""sep_plant: part of sep (separation-based, data-driven LQG for large partially observed systems): plant protocol, plants, scenarios, topic contract."""
