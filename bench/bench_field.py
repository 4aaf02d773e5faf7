"""Online cost of the reconstructed field at scale: Phi (g_k a), the field messages (no assertions).

What the estimator node does per step for field_estimate (PointCloud2) and
field_estimate_image (Image), measured on the product's own code path, without ROS
networking (rclpy message classes and rclpy.serialization only; no rclpy.init, no node):

* mean: `KalmanFilter.field_deviation()` = `PODFieldMap.apply(k, a)` = (a g_k') Phi', the
  reconstruction Phi (g_k a) of the field deviation; and `EstimatorCore.field_estimate()` as the
  node calls it after an on-schedule update (fbar_k + Phi g_k a, with the per-node std read from
  the design's precomputed `LQG.field_std`: no std computation per step on schedule).
* std off schedule: `EstimatorCore.field_estimate()` after a skipped measurement (gap), where
  the std is computed per step, `PODFieldMap.std(k, P)` = rowsum((Phi g_k L)^2), P = L L'.
* float32: the same two calls on an `EstimatorCore(..., field_precision="float32")`, the
  estimator node's parameter field_precision:=float32 (`ltv.Float32Reconstruction`: the product
  from a float32 copy of Phi, the result float64).
* messages: `contract.CloudBuilder.build` (contract PointCloud2, 5 float64 channels, 40 B per
  node) and `contract.field_image` (sensor_msgs/Image 32FC1 via `topics.image_of_field`), each
  built and then serialized with rclpy.serialization.serialize_message (the conversion `publish`
  performs); sizes are the serialized CDR bytes. The node builds these only while the topic has
  a subscriber (estimator_node.py `_emit`: `get_subscription_count() > 0`); with none, the cost
  is the count check alone.
* step share: (field_estimate + build + serialize) / (dt / real_time_factor) with dt of the
  plate scenario (sep_plant/scenarios/plate.yaml, 0.5 s), at real_time_factor 1 and 10; byte
  rate of one subscribed topic at 1/dt (x10 at real_time_factor 10).

Rows: plate grids (HeatPlate coordinates and field name) x field-basis rank r_f, with a random
orthonormal Phi (QR) and random coefficients g (N+1, r_f, n_r), n_r = 20. Ranks: 68 (the plate
64^2 scenario's field map, compressed at the default field_map_tol 1e-5), 155 (Allen-Cahn's, the
largest of the shipped scenarios) and 220 (the plate's map uncompressed, as sep 0.3's design
files held it); the per-step cost
does not depend on N, so the horizon is short (`--steps`). Timing: time.perf_counter per call,
`--reps` calls after warm-up, one BLAS thread (threadpoolctl), p50 / p99 in ms.

    OPENBLAS_NUM_THREADS=1 python bench/bench_field.py                   # 64^2, 128^2, 256^2 (~1 min)
    OPENBLAS_NUM_THREADS=1 python bench/bench_field.py --grids 256 --reps 500
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
for p in ("sep_plant", "sep_estimator", "sep_control"):
    sys.path.insert(0, str(REPO / p))

N_R = 20
RANKS = (68, 155, 220)
RTFS = (1.0, 10.0)


def timed(fn, reps: int, warm: int = 5) -> np.ndarray:
    """Seconds per call of fn() over `reps` calls after `warm` warm-up calls."""
    for _ in range(warm):
        fn()
    out = np.empty(reps)
    for i in range(reps):
        t = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t
    return out


def ms(t: np.ndarray, q: float) -> float:
    return float(np.percentile(t, q) * 1e3)


def make_core(plant, r_f: int, n_steps: int, rng: np.random.Generator):
    """A factory of EstimatorCores (field_precision as its argument) on one synthetic model."""
    # a PODFieldMap of rank r_f (random orthonormal Phi), a random model
    from sep_estimator.estimator_core import EstimatorCore
    from sep_estimator.ltv import LQG, KalmanSchedule, LTVModel, PODFieldMap

    N, nf, nu, ny = n_steps, plant.n_field, plant.n_u, plant.n_y
    Phi = np.ascontiguousarray(np.linalg.qr(rng.standard_normal((nf, r_f)))[0])
    g = rng.standard_normal((N + 1, r_f, N_R)) / np.sqrt(N_R)
    M = rng.standard_normal((N + 1, N_R, N_R)) / np.sqrt(N_R)
    P = M @ M.transpose(0, 2, 1) + 1e-3 * np.eye(N_R)          # PSD covariances
    model = LTVModel(A=0.9 * np.broadcast_to(np.eye(N_R), (N, N_R, N_R)).copy(),
                     B=rng.standard_normal((N, N_R, nu)), C=rng.standard_normal((N + 1, ny, N_R)),
                     G=PODFieldMap(Phi, g), dims=np.full(N + 1, N_R, dtype=np.int64))
    kf = KalmanSchedule(L=rng.standard_normal((N + 1, N_R, ny)) * 0.1, P_post=P, P_prior=P.copy())
    lqg = LQG("rom_lqg", model, np.zeros((N, nu, N_R)), kf, np.eye(nu), np.eye(ny))   # field_std: precomputed here
    u_nom, y_nom = np.zeros((N, nu)), np.zeros((N + 1, ny))
    field_nom = 100.0 + rng.standard_normal((N + 1, nf))
    return (lambda precision="float64": EstimatorCore(lqg, u_nom, y_nom, field_nom, field_precision=precision),
            y_nom, u_nom)


def bench_row(n_side: int, r_f: int, reps: int, n_steps: int, dt: float, rng) -> tuple[dict, dict, dict]:
    from rclpy.serialization import serialize_message
    from sep_plant.ros import contract as c
    from sep_plant.plants.heat import HeatPlate

    plant = HeatPlate(nodes=(n_side, n_side))
    new_core, y_nom, u_nom = make_core(plant, r_f, n_steps, rng)
    k = 1

    def on_schedule(precision: str):
        core = new_core(precision)                   # on schedule, after the update of step k
        core.measurement(0, y_nom[0] + 0.1)
        core.applied(0, u_nom[0])
        core.measurement(k, y_nom[k] + 0.1)
        return core

    on, on32 = on_schedule("float64"), on_schedule("float32")
    off = new_core()                                 # off schedule: step 1 missed, update at k + 1
    off.measurement(0, y_nom[0] + 0.1)
    off.applied(0, u_nom[0])
    off.measurement(k + 1, y_nom[k + 1] + 0.1)
    assert on.kf.on_schedule and on.kf.posterior and not off.kf.on_schedule

    t_mean = timed(on.kf.field_deviation, reps)
    t_est = timed(on.field_estimate, reps)
    t_off = timed(off.field_estimate, reps)
    t_mean32 = timed(on32.kf.field_deviation, reps)
    t_est32 = timed(on32.field_estimate, reps)
    err32 = float(np.abs(on32.kf.field_deviation() - on.kf.field_deviation()).max()
                  / np.abs(on.kf.field_deviation()).max())

    f, std = on.field_estimate()
    cloud = c.CloudBuilder(plant.field_coordinates(), plant.field_name)
    t_cb = timed(lambda: cloud.build(k, dt, f, std), reps)
    msg = cloud.build(k, dt, f, std)
    t_cs = timed(lambda: serialize_message(msg), reps)
    cloud_bytes = len(serialize_message(msg))
    t_ib = timed(lambda: c.field_image(k, dt, f, plant.grid_shape), reps)
    img = c.field_image(k, dt, f, plant.grid_shape)
    t_is = timed(lambda: serialize_message(img), reps)
    image_bytes = len(serialize_message(img))

    name = f"{n_side}x{n_side} r_f={r_f}"
    rec = {"n_field": plant.n_field, "r_f": r_f,
           "mean p50 ms": ms(t_mean, 50), "mean p99 ms": ms(t_mean, 99),
           "est p50 ms": ms(t_est, 50), "est p99 ms": ms(t_est, 99),
           "std-off p50 ms": ms(t_off, 50), "std-off p99 ms": ms(t_off, 99)}
    f32 = {"n_field": plant.n_field, "r_f": r_f, "mean p50 ms": ms(t_mean32, 50), "mean p99 ms": ms(t_mean32, 99),
           "est p50 ms": ms(t_est32, 50), "est p99 ms": ms(t_est32, 99), "float32 rel. err": f"{err32:.1e}"}
    est = ms(t_est, 50)
    cloud_ms = est + ms(t_cb, 50) + ms(t_cs, 50)
    image_ms = est + ms(t_ib, 50) + ms(t_is, 50)
    msgs = {"n_field": plant.n_field, "r_f": r_f,
            "pc2 build ms": ms(t_cb, 50), "pc2 ser ms": ms(t_cs, 50), "pc2 B": cloud_bytes,
            "img build ms": ms(t_ib, 50), "img ser ms": ms(t_is, 50), "img B": image_bytes}
    for rtf in RTFS:
        msgs[f"pc2 %step rtf{rtf:g}"] = 100.0 * cloud_ms / (1e3 * dt / rtf)
        msgs[f"img %step rtf{rtf:g}"] = 100.0 * image_ms / (1e3 * dt / rtf)
    msgs["pc2 MB/s"] = cloud_bytes / dt / 1e6
    msgs["img MB/s"] = image_bytes / dt / 1e6
    return {name: rec}, {f"{name} float32": f32}, {name: msgs}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--reps", type=int, default=200, help="timed calls per measurement (after 5 warm-up calls)")
    ap.add_argument("--grids", type=int, nargs="+", default=[64, 128, 256],
                    help="plate grid sides n (n x n nodes)")
    ap.add_argument("--ranks", type=int, nargs="+", default=list(RANKS), help="field-basis ranks r_f")
    ap.add_argument("--steps", type=int, default=8, help="horizon N of the synthetic model (cost per step does not depend on it)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)

    from threadpoolctl import threadpool_limits
    from sep_control.evaluation.metrics import format_table
    from sep_plant.scenario import load_scenario

    dt = float(load_scenario(REPO / "sep_plant" / "scenarios" / "plate.yaml").plant_config["dt"])
    rng = np.random.default_rng(args.seed)
    recon: dict = {}
    msgs: dict = {}
    with threadpool_limits(limits=1):
        for n in args.grids:
            f32_rows: dict = {}
            for r in args.ranks:
                rec, f32, m = bench_row(n, r, args.reps, args.steps, dt, rng)
                recon.update(rec)
                f32_rows.update(f32)
                msgs.update(m)
            recon.update(f32_rows)
    print(f"field reconstruction, n_r = {N_R}, one BLAS thread, {args.reps} reps (target: mean <= 1 ms at 65536 nodes)")
    print("mean: Phi (g_k a) (PODFieldMap.apply); est: EstimatorCore.field_estimate() on schedule (std = "
          "precomputed lookup); std-off: field_estimate() off schedule (PODFieldMap.std per step)")
    print("float32: the same with field_precision float32 (rel. err: max |float32 - float64| / max |float64| "
          "of the deviation)")
    print(format_table(recon, ["n_field", "r_f", "mean p50 ms", "mean p99 ms", "est p50 ms",
                               "est p99 ms", "std-off p50 ms", "std-off p99 ms", "float32 rel. err"]))
    print()
    print(f"field messages (built only when subscribed): pc2 = PointCloud2 (CloudBuilder.build), img = Image 32FC1 "
          f"(field_image); ser = serialize_message; B = serialized bytes;\n%step = (est + build + ser) p50 / "
          f"(dt / rtf), plate dt = {dt:g} s; MB/s at 1/dt (x10 at rtf 10)")
    print(format_table(msgs, list(next(iter(msgs.values())).keys())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
