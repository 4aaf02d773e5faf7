"""`sep`: one command for sep's tools (placeholder of the packaging branch).

PLACEHOLDER: the CLI branch replaces this file with the real `sep` command; this one only
dispatches to the existing per-tool modules so that the `sep` console script, the venv launcher
and the ROS-free install can be tested.  See docs/reference/cli.md.
"""
from __future__ import annotations

import importlib
import sys

from sep_control import __version__

# subcommand -> module with main(argv); the ROS one is imported only when called
COMMANDS = {
    "design": "sep_control.cli.design",
    "evaluate": "sep_control.cli.evaluate",
    "validate": "sep_control.cli.validate",
    "demo": "sep_control.cli.demo",
    "analyze": "sep_control.cli.analyze",
    "record": "sep_control.ros.record_node",
}
USAGE = f"usage: sep [--version] {{{','.join(COMMANDS)}}} ..."


def main(argv: list[str] | None = None) -> int:
    """Run ``sep <subcommand> ARGS`` and return its exit status."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == ["--version"]:
        print(f"sep {__version__}")
        return 0
    if args[:1] in (["-h"], ["--help"]):
        print(USAGE)
        return 0
    if not args or args[0] not in COMMANDS:
        print(f"{USAGE}\nsep: error: choose a subcommand", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[args[0]])
    return int(module.main(args[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
