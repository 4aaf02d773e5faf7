"""`sep analyze BAG... [--design FILE] [--out DIR] [--json PATH]`: report on recorded episodes.

Any plant: one bag gives its metrics (docs/method.md) and the paper's figures (lines for 1-D
plants, heat maps for grid plants, a frame of the image topic when the bag has one); several
bags (e.g. 50 seeded episodes) give one row per episode plus pooled statistics comparable to
the offline Monte Carlo table; so does one bag of several episodes (a plant with ``episodes`` != 1:
rows BAG.e0, BAG.e1, ..., `sep_control.bags.episodes`). Without --design the objective is the bag's own scenario's and
nominal comparisons are skipped. Prints the metrics table and where the report is; exits 2
with a one-line message on bad input (missing/corrupt/truncated bag, unreadable design file,
design file of another plant).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from sep_plant.topics import NAMESPACE

from sep_control.cli.common import fail, groups, legacy_main
from sep_control.compute.progress import RunSteps, bars_wanted

HELP = "report on recorded episodes (rosbag2 bags): metrics, figures, JSON"
DESCRIPTION = ("Analyse rosbag2 bags recorded from the sep topic graph: metrics (docs/method.md), a Markdown "
               "report with figures, optional JSON. Works for any plant of the plant protocol; several bags "
               "give one row per episode and pooled statistics.\n\n"
               "Example:  sep analyze out/demo/bag --design out/demo/design.npz")


def configure(parser: argparse.ArgumentParser) -> None:
    """The options of `sep analyze`."""
    basic, advanced = groups(parser)
    basic.add_argument("bags", nargs="+", metavar="BAG",
                       help="bag directory (metadata.yaml + .mcap/.db3) or a lone .mcap/.db3 file")
    basic.add_argument("--design", metavar="FILE",
                       help="design file (.npz): its objective and nominal (default: the bag's scenario, no nominal)")
    basic.add_argument("--out", metavar="DIR",
                       help="report directory (default: <BAG>_report for one bag, <parent>/aggregate_report for many)")
    basic.add_argument("--json", metavar="PATH", help="write the metrics as JSON (metrics (docs/method.md))")
    basic.add_argument("--quiet", action="store_true",
                       help="no progress bar (drawn over the bags only when stderr is a terminal)")
    advanced.add_argument("--namespace", default=None,
                          help=f"topic namespace of the graph (default: the bag's own, found from its measurements "
                               f"topic; {NAMESPACE} for sep's nodes, slab for bags of sep 0.1)")
    advanced.add_argument("--allow-mismatch", action="store_true",
                          help="analyse bags of another plant than the design file (flagged in the report)")
    advanced.add_argument("--allow-truncated", action="store_true",
                          help="analyse what can be recovered from a truncated bag (crash during recording)")
    advanced.add_argument("--no-figures", action="store_true", help="write report.md without figures")


def run(args: argparse.Namespace) -> int:
    from sep_control.bags.report import LATENCY_NOTE, metrics_rows, write_report
    from sep_control.evaluation import metrics as M

    t0 = time.perf_counter()
    rep, default_out = analysed(args)
    t_analysis = time.perf_counter() - t0
    rows = metrics_rows(rep)
    out = Path(args.out) if args.out else default_out
    try:
        path = write_report(rep, out, figures=not args.no_figures)
        if args.json:
            M.write_metrics_json(args.json, rows)
    except OSError as exc:
        fail(f"cannot write the report: {exc}")
    keys = [k for k in M.JSON_KEYS if any(r.get(k) is not None for r in rows.values())]
    print(M.format_table(rows, keys))
    print_notes(rep)
    print(f"({LATENCY_NOTE})")
    print(f"analysis {t_analysis:.2f} s, total {time.perf_counter() - t0:.2f} s")
    print(f"report: {path}")
    if args.json:
        print(f"json: {args.json}")
    return 0


class ProgressBar:
    """`aggregate`'s ``on_progress(steps_done, steps_total)`` drawn as a `RunSteps` bar, opened
    once the total is known (from the design, else after the first bag); drawn when `enabled`."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self.bar: RunSteps | None = None

    def __call__(self, done: int, total: int | None) -> None:
        if total is None:
            return
        if self.bar is None:
            self.bar = RunSteps(total, "analyze (run-steps)", self.enabled)
        self.bar.add(done - self.bar.done)

    def __enter__(self) -> "ProgressBar":
        return self

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()


def analysed(args: argparse.Namespace):
    """(report, default report directory) of the bags: one bag's `analyze`, or `aggregate` over
    several (with a bar in run-steps); exit 2 on a bad bag or design."""
    from sep_control.bags.analysis import AnalysisError, aggregate
    from sep_control.bags.episodes import analyze_episodes
    from sep_control.bags.storage import BagError
    from sep_estimator.design_file import DesignFileError, load_design

    try:
        design = load_design(args.design) if args.design else None
        kw = dict(allow_mismatch=args.allow_mismatch, allow_truncated=args.allow_truncated, namespace=args.namespace)
        if len(args.bags) == 1:     # a bag of several episodes: a row each and the pooled row
            rep = analyze_episodes(args.bags[0], design, **kw)
            return rep, Path(str(Path(args.bags[0]).resolve()).removesuffix(".mcap").removesuffix(".db3") + "_report")
        with ProgressBar(bars_wanted(args.quiet)) as bar:
            rep = aggregate(args.bags, design, on_progress=bar, **kw)
        return rep, Path(args.bags[0]).resolve().parent / "aggregate_report"
    except (BagError, AnalysisError, DesignFileError) as exc:
        fail(str(exc))


def print_notes(rep) -> None:
    """Missing topics, plant mismatches and truncated bags, one line each."""
    for r in getattr(rep, "reports", [rep]):
        if r.episode.missing:
            print(f"note: {r.name}: missing topics {', '.join(r.episode.missing)}")
        if r.mismatch:
            print(f"WARNING: {r.name}: the bag's plant differs from the design file's: {'; '.join(r.mismatch)}")
        if r.model_mismatch:
            print(f"model_mismatch: {r.name}: the design ran on another plant than its model: "
                  f"{'; '.join(r.model_mismatch)}")
        if not r.episode.complete:
            print(f"note: {r.name}: truncated bag, analysed what was recovered")


def main(argv: list[str] | None = None) -> int:
    """The old `analyze` command: `sep analyze` with a deprecation line."""
    return legacy_main("analyze", argv)


if __name__ == "__main__":
    sys.exit(main())
