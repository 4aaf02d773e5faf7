"""`sep`: one command for the offline tools and the demo.

    sep design | evaluate | validate | demo | analyze | record | plants | check-plant [options]
    sep --version

Each subcommand's ``--help`` explains it, its options in a Basic and an Advanced group
(docs/reference/cli.md). Errors: ``sep <subcommand>: error: <message>`` on stderr, exit 2 for
bad input and 1 for a failed task. `sep record` is the recorder node's own command line; it is
imported only when called, so the other subcommands never import rclpy.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from sep_control.cli.common import Formatter, set_prog

#: subcommand -> (module, configure, run, help, description); record is the recorder's own parser
SUBCOMMANDS = {
    "design": ("sep_control.cli.design", "configure", "run", "HELP", "DESCRIPTION"),
    "evaluate": ("sep_control.cli.evaluate", "configure", "run", "HELP", "DESCRIPTION"),
    "validate": ("sep_control.cli.validate", "configure", "run", "HELP", "DESCRIPTION"),
    "demo": ("sep_control.cli.demo", "configure", "run", "HELP", "DESCRIPTION"),
    "analyze": ("sep_control.cli.analyze", "configure", "run", "HELP", "DESCRIPTION"),
    "plants": ("sep_control.cli.plants", "configure_plants", "run_plants", "PLANTS_HELP", "PLANTS_DESCRIPTION"),
    "check-plant": ("sep_control.cli.plants", "configure_check", "run_check", "CHECK_HELP", "CHECK_DESCRIPTION"),
}
RECORD_HELP = "record the sep topics of an episode to a rosbag2 bag (the recorder node; `sep record --help`)"


def version() -> str:
    """sep's version (one definition for the three packages)."""
    try:
        from sep_plant import __version__
    except ImportError:
        from sep_control import __version__
    return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sep", formatter_class=Formatter,
        description="sep: separation-based, data-driven LQG for large partially observed systems.\n"
                    "Offline: design a controller from a black-box simulator, evaluate and validate it;\n"
                    "online: run it over ROS 2 topics (demo, record) and analyse the bags.",
        epilog="`sep SUBCOMMAND --help` explains each one (docs/reference/cli.md).")
    parser.add_argument("--version", action="version", version=f"sep {version()}")
    sub = parser.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)
    parser.set_defaults(_subparsers={})
    for name, (module, configure, run, help_name, desc_name) in SUBCOMMANDS.items():
        mod = importlib.import_module(module)
        p = sub.add_parser(name, help=getattr(mod, help_name), description=getattr(mod, desc_name),
                           formatter_class=Formatter)
        getattr(mod, configure)(p)
        p.set_defaults(_run=getattr(mod, run))   # (demo has a --run option)
        parser.get_default("_subparsers")[name] = p
    sub.add_parser("record", help=RECORD_HELP, add_help=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``sep argv`` (sys.argv[1:] when None); returns the exit status (bad input exits 2
    through SystemExit, as argparse does)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv else ""
    if command == "record":
        from sep_control.ros.record_node import main as record_main

        return record_main(argv[1:])
    set_prog(f"sep {command}" if command in SUBCOMMANDS else "sep")
    args, extra = build_parser().parse_known_args(argv)
    if extra:       # the subcommand's error (argparse would report it as the top parser's)
        args._subparsers[args.command].error(f"unrecognized arguments: {' '.join(extra)}")
    return args._run(args)


if __name__ == "__main__":
    sys.exit(main())
