"""The end of a `sep demo` episode: its metrics from the nodes' files, the bag's analysis, and
the printed summary. ROS-free (reads the files the nodes wrote)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from sep_control.cli.processes import Children


def episode_metrics(design, traj: Path, files: dict, three: bool) -> dict:
    """The episode's metrics (docs/method.md) from the plant's trajectory file and the nodes'
    summaries: cost, band, RMS, deadline misses, rejected messages, latencies, fallbacks."""
    import numpy as np

    from sep_control.evaluation import metrics as M
    z = np.load(traj, allow_pickle=False)
    F, U = z['F'], z['U']
    plant = json.loads(files['plant'].read_text())
    if three:
        est = json.loads(files['estimator'].read_text())
        lqr = json.loads(files['lqr'].read_text())
    else:
        both = json.loads(files['lqg'].read_text())
        est, lqr = both['estimator'], both['lqr']
    out = M.summarize(F[None], U[None], design.nominal.field, design.objective)
    out.update({'deadline_misses': plant['deadline_misses'],
                'rejected_messages': plant['rejected_messages'] + est['rejected_messages'] + lqr['rejected_messages'],
                # the plant's own clock: publish of y_k to arrival of command k; with a bag the
                # demo replaces latency_p50_s/p99_s by the recorder's (docs/method.md)
                'latency_plant_p50_s': plant['latency_p50_s'], 'latency_plant_p99_s': plant['latency_p99_s'],
                'latency_p50_s': plant['latency_p50_s'], 'latency_p99_s': plant['latency_p99_s'],
                'lqr_fallbacks': lqr['fallbacks'], 'wall_s': plant['wall_s'], 'nis_mean': est.get('nis_mean'),
                'controller': lqr['controller'], 'mpc_fallbacks': lqr.get('mpc_fallbacks'),
                'mpc_qp_steps': lqr.get('mpc_qp_steps'), 'mpc_qp_p99_s': lqr.get('mpc_qp_p99_s'),
                'estimator_compute_p50_s': est.get('compute_p50_s'),
                'rejected_by_node': {'plant': plant.get('rejected_by_reason', {}),
                                     'estimator': est.get('rejected_by_reason', {}),
                                     'lqr': lqr.get('rejected_by_reason', {})}})
    return out


def run_analysis(kids: Children, bag: Path, design_file: Path, out: Path, log) -> tuple[Path | None, dict]:
    """`sep analyze` of the episode's bag as a child process (its output in logs/analyze.log):
    (the report, the bag's metrics), or (None, {}) when it failed."""
    report_dir = out / 'report'
    js = out / 'bag_metrics.json'
    js.unlink(missing_ok=True)
    kids.start('analyze', [sys.executable, '-m', 'sep_control.cli.main', 'analyze', str(bag), '--design',
                           str(design_file), '--out', str(report_dir), '--json', str(js), '--quiet'])
    if kids.wait('analyze', 120) != 0:
        log(f'analyze failed:\n{kids.tail("analyze")}')
        return None, {}
    try:
        data = json.loads(js.read_text())
    except (OSError, json.JSONDecodeError):
        data = {}
    if isinstance(data, list):
        data = data[0] if data else {}
    if isinstance(data, dict) and len(data) == 1 and isinstance(next(iter(data.values())), dict):
        data = next(iter(data.values()))
    report = next(iter(sorted(report_dir.glob('*.md'))), report_dir) if report_dir.exists() else None
    return report, data if isinstance(data, dict) else {}


def print_metrics(m: dict, design, name: str = 'rom_lqg') -> None:
    """The episode's metrics table and one line on the band, the wall time and the fallbacks."""
    import numpy as np

    from sep_control.evaluation import metrics as M
    keys = [k for k in M.JSON_KEYS if k in m]
    info, obj = design.info, design.objective
    horizon = design.n_steps * info.dt
    k0, k1 = obj.window
    flat = np.ravel(obj.target)
    target = f'{flat[0]:g}' if (flat == flat[0]).all() else 'the target pattern'
    unit = f' {info.field_unit}' if info.field_unit else ''
    band = f"{target} +- {obj.band:g}{unit} over t = {k0 * info.dt:g}..{k1 * info.dt:g} s"
    if obj.holds is not None:                  # a recipe: every hold's own band
        band = "every hold's band: " + ", ".join(f"+- {b:g}{unit} over t = {a * info.dt:g}..{c * info.dt:g} s"
                                                 for a, c, b in obj.holds)
    print()
    print(M.format_table({f'{name} (topics)': m}, keys))
    print(f"\nin band (whole field within {band}): "
          f"{'yes' if m['in_band'] >= 1 else 'NO'}; episode {m['wall_s']:.2f} s wall for {horizon:g} s simulated "
          f"({horizon / m['wall_s']:.1f}x real time; {m['total_wall_s']:.1f} s with start-up); "
          f"LQR nominal fallbacks {m['lqr_fallbacks']}"
          + (f"; MPC: {m['mpc_qp_steps']} QPs (p99 {(m['mpc_qp_p99_s'] or 0) * 1e3:.2f} ms), "
             f"{m['mpc_fallbacks']} fallbacks to the clipped LQR" if m.get('controller') == 'rom_mpc' else ''))
