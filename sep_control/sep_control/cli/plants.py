"""`sep plants` and `sep check-plant`: which plant types this installation knows, and whether a
scenario's plant meets the plant protocol (docs/plants.md)."""
from __future__ import annotations

import argparse

from sep_control.cli.common import groups, plant_or_exit, scenario_or_exit

PLANTS_HELP = "list the plant types this installation knows (built-ins and `sep.plants` entry points)"
PLANTS_DESCRIPTION = """\
List the plant types a scenario's `plant: {type: ...}` may name: the built-in plants and those
installed under the `sep.plants` entry-point group, each with its module:class. Any other
importable class is named as "package.module:ClassName" (docs/plants.md).
"""
CHECK_HELP = "check a scenario's plant against the plant protocol"
CHECK_DESCRIPTION = """\
Build the scenario's plant and run the plant protocol's checks on a small batch (dimensions,
names, config() round trip, shapes, finiteness, determinism, batch vs one by one, noise on the
inputs; docs/plants.md). Prints "ok" and the plant's description, or every problem found
(exit 2).

Example:  sep check-plant --scenario examples/burgers/scenario.yaml
"""


def configure_plants(parser: argparse.ArgumentParser) -> None:
    """`sep plants` has no options."""


def run_plants(args: argparse.Namespace) -> int:
    from sep_plant.plants import BUILTIN, available

    known = available()
    width = max(map(len, known), default=0)
    for name, target in sorted(known.items()):
        kind = "built-in" if name in BUILTIN else "entry point"
        print(f"{name:{width}s}  {target}  ({kind})")
    return 0


def configure_check(parser: argparse.ArgumentParser) -> None:
    basic, _ = groups(parser)
    basic.add_argument("--scenario", metavar="FILE", help="scenario YAML (default: the reference scenario)")


def run_check(args: argparse.Namespace) -> int:
    from sep_plant.protocol import PlantInfo

    scenario = scenario_or_exit(args.scenario)
    plant = plant_or_exit(scenario, args.scenario or "reference scenario")
    print(f"ok: {describe(scenario.plant_type, PlantInfo.of(plant))}")
    return 0


def describe(plant_type: str, info) -> str:
    """One line: type, dimensions, time step, field."""
    grid = f", grid {' x '.join(map(str, info.grid_shape))}" if info.grid_shape else ""
    unit = f" [{info.field_unit}]" if info.field_unit else ""
    return (f"plant {plant_type}: n_x = {info.n_x}, {info.n_u} inputs, {info.n_y} outputs, "
            f"{info.n_field} field nodes ({info.field_name}{unit}{grid}), dt = {info.dt:g} s, "
            f"noise channels {info.n_w if info.n_w is not None else info.n_u}"
            + (" (opaque states: no EnKF belief, no full-order oracle)" if info.state_is_opaque else ""))
