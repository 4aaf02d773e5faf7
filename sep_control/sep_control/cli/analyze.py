"""`analyze BAG... [--design FILE] [--out DIR] [--json PATH]`: report on recorded episodes.

Any plant: one bag gives its metrics (docs/method.md) and the paper's figures (lines for 1-D
plants, heat maps for grid plants, a frame of the image topic when the bag has one); several
bags (e.g. 50 seeded episodes) give one row per episode plus pooled statistics comparable to
the offline Monte Carlo table. Without --design the objective is the bag's own scenario's and
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

EXIT_BAD_INPUT = 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="analyze",
        description="Analyse rosbag2 bags recorded from the sep topic graph: metrics (docs/method.md), "
                    "Markdown report with figures, optional JSON. Works for any plant of the plant protocol.")
    p.add_argument("bags", nargs="+", metavar="BAG",
                   help="bag directory (metadata.yaml + .mcap/.db3) or a lone .mcap/.db3 file")
    p.add_argument("--design", metavar="FILE",
                   help="design file (.npz): its objective and nominal (default: the bag's scenario, no nominal)")
    p.add_argument("--out", metavar="DIR",
                   help="report directory (default: <BAG>_report for one bag, <parent>/aggregate_report for many)")
    p.add_argument("--json", metavar="PATH", help="write the metrics as JSON (metrics (docs/method.md))")
    p.add_argument("--namespace", default=None,
                   help=f"topic namespace of the graph (default: the bag's own, found from its measurements topic; "
                        f"{NAMESPACE} for sep's nodes, slab for bags of sep 0.1)")
    p.add_argument("--allow-mismatch", action="store_true",
                   help="analyse bags of another plant than the design file (flagged in the report)")
    p.add_argument("--allow-truncated", action="store_true",
                   help="analyse what can be recovered from a truncated bag (crash during recording)")
    p.add_argument("--no-figures", action="store_true", help="write report.md without figures")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from sep_control.evaluation import metrics as M
    from sep_control.bags.analysis import AnalysisError, aggregate, analyze
    from sep_control.bags.storage import BagError

    t0 = time.perf_counter()
    try:
        design = None
        if args.design:
            from sep_estimator.design_file import DesignFileError, load_design

            try:
                design = load_design(args.design)
            except DesignFileError as exc:
                raise AnalysisError(str(exc)) from None
        kw = dict(allow_mismatch=args.allow_mismatch, allow_truncated=args.allow_truncated,
                  namespace=args.namespace)
        if len(args.bags) == 1:
            rep = analyze(args.bags[0], design, **kw)
            rows = {rep.name: rep.metrics}
            default_out = Path(str(Path(args.bags[0]).resolve()).removesuffix(".mcap").removesuffix(".db3") + "_report")
        else:
            rep = aggregate(args.bags, design, **kw)
            rows = {**rep.rows, "all episodes": rep.metrics}
            default_out = Path(args.bags[0]).resolve().parent / "aggregate_report"
    except (BagError, AnalysisError) as exc:
        print(f"analyze: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    t_analysis = time.perf_counter() - t0

    from sep_control.bags.report import LATENCY_NOTE, write_report

    out = Path(args.out) if args.out else default_out
    try:
        path = write_report(rep, out, figures=not args.no_figures)
        if args.json:
            M.write_json(args.json, rows)
    except OSError as exc:
        print(f"analyze: error: cannot write the report: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    keys = [k for k in M.JSON_KEYS if any(r.get(k) is not None for r in rows.values())]
    print(M.format_table(rows, keys))
    for r in getattr(rep, "reports", [rep]):
        if r.episode.missing:
            print(f"note: {r.name}: missing topics {', '.join(r.episode.missing)}")
        if r.mismatch:
            print(f"WARNING: {r.name}: the bag's plant differs from the design file's: {'; '.join(r.mismatch)}")
        if not r.episode.complete:
            print(f"note: {r.name}: truncated bag, analysed what was recovered")
    print(f"({LATENCY_NOTE})")
    print(f"analysis {t_analysis:.2f} s, total {time.perf_counter() - t0:.2f} s")
    print(f"report: {path}")
    if args.json:
        print(f"json: {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
