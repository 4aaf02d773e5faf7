"""Before the GPU measurements: what the device is, whether every CuPy call of the resident
path works there, what transfers and kernel compilation cost, and a small design and Monte
Carlo on the GPU against the CPU's (the check the tests make on the emulated device, here on
the real one). Prints one line per check ("ok" or "FAILED: why"); asserts nothing, exits 0.

    python bench/device_preflight.py            # needs CuPy and a GPU (bench/device_run.sh runs it)
    python bench/device_preflight.py --emulated # the tests' emulator: checks this script without a GPU
"""
from __future__ import annotations

import argparse
import sys
import time
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests"))


def check(name: str, fn) -> object:
    t0 = time.perf_counter()
    try:
        out = fn()
    except Exception as exc:                          # report and go on: one run must tell everything
        print(f"  {name}: FAILED ({time.perf_counter() - t0:.2f} s): {type(exc).__name__}: {exc}", flush=True)
        traceback.print_exc(limit=4, file=sys.stdout)
        return None
    print(f"  {name}: ok ({time.perf_counter() - t0:.2f} s){'' if out is None else ': ' + str(out)}", flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--emulated", action="store_true", help="the tests' CPU emulator instead of CuPy")
    ap.add_argument("--skip-design", action="store_true", help="no small design on the device")
    args = ap.parse_args()
    import numpy as np

    from sep_plant.device import device_memory, device_runs_per_batch, on_device, synchronize
    from sep_plant.plants import make_plant

    if args.emulated:
        from device_guard import guard as xp
    else:
        import cupy as xp
        dev = xp.cuda.Device()
        props = xp.cuda.runtime.getDeviceProperties(dev.id)
        print(f"cupy {xp.__version__}, CUDA runtime {xp.cuda.runtime.runtimeGetVersion()}, driver "
              f"{xp.cuda.runtime.driverGetVersion()}, device {dev.id}: {props['name'].decode()}, compute "
              f"capability {dev.compute_capability}, {props['totalGlobalMem'] / 2**30:.1f} GiB", flush=True)
    print(f"numpy {np.__version__}; free device memory {device_memory(xp) / 2**30:.1f} GiB", flush=True)
    rng = np.random.default_rng(0)

    print("CuPy calls of the resident path:")
    A = rng.standard_normal((40, 3000))
    d = xp.asarray(A)
    check("index by a host int array", lambda: float(abs(d[np.array([0, 5])].get() - A[[0, 5]]).max()))
    check("row broadcast into a slice", lambda: d.__setitem__(slice(2, 4), d[0]))
    check("svd of a wide block (b x n_f)", lambda: float(abs(xp.linalg.svd(d, full_matrices=False)[1].get()
                                                           - np.linalg.svd(d.get(), compute_uv=False)).max()))
    check("qr of a tall block (n_f x k)", lambda: xp.linalg.qr(d.T)[0].shape)
    check("norm, einsum, std(ddof=1), count_nonzero", lambda: (float(xp.linalg.norm(d)),
                                                               float(xp.einsum("ij,ij->i", d, d).max()),
                                                               float(d.std(axis=0, ddof=1).max()),
                                                               int(xp.count_nonzero(d > 0))))
    check("multiply into a slice (out=)", lambda: xp.multiply(d[:4], np.float64(2.0), out=d[4:8]).shape)
    check("float32 product to float64", lambda: str((d.astype(np.float32) @ d.T.astype(np.float32))
                                                    .astype(np.float64).dtype))
    check("float64 is the default dtype", lambda: str(xp.zeros(3).dtype))
    check("products with an empty basis (n x 0)", lambda: (d.T @ xp.zeros((40, 0))).shape)

    def basis(n_f: int = 1_000_000, b: int = 144, blocks: int = 3, method: str = "gram"):
        from sep_control.design.basis import IncrementalBasis
        B = IncrementalBasis(n_f, 1e-8, xp=xp, method=method)
        modes = xp.asarray(rng.standard_normal((300, n_f)) / np.sqrt(n_f))
        times = []
        for _ in range(blocks):
            D = xp.asarray(rng.standard_normal((b, 300)) * np.logspace(0, -6, 300)) @ modes
            synchronize(xp)
            t0 = time.perf_counter()
            C = B.add(D)
            synchronize(xp)
            times.append(time.perf_counter() - t0)
            err = float(xp.abs(C @ B.phi.T - D).max() / xp.abs(D).max())
        return (f"rank {B.rank}, add of {b} x {n_f:.0e} blocks {', '.join(f'{t:.2f}' for t in times)} s, "
                f"rebuild error {err:.1e}")
    for method, what in (("gram", "Gram matrices, CholeskyQR2"), ("svd", "plan 0.8: SVD via QR, QR")):
        check(f"field basis on the device (10^6-long blocks, {method}: {what}, projections)",
              (lambda m=method: basis(method=m)) if not args.emulated else (lambda m=method: basis(20_000, 36, method=m)))

    def gflops():
        B = xp.asarray(rng.standard_normal((2000, 20000)))
        B @ B.T
        synchronize(xp)
        t0 = time.perf_counter()
        for _ in range(3):
            B @ B.T
        synchronize(xp)
        return f"{3 * 2 * 2000**2 * 20000 / (time.perf_counter() - t0) / 1e9:.0f} GFlop/s float64 (gemm A A')"
    check("float64 gemm rate", gflops)

    def bandwidth():
        H = rng.standard_normal(32 << 20 >> 3)              # 32 MB pageable
        t0 = time.perf_counter()
        D = xp.asarray(H)
        synchronize(xp)
        up = time.perf_counter() - t0
        t0 = time.perf_counter()
        D.get()
        down = time.perf_counter() - t0
        return f"32 MB pageable: up {H.nbytes / up / 1e9:.1f} GB/s, down {H.nbytes / down / 1e9:.1f} GB/s"
    check("host <-> device bandwidth", bandwidth)

    print("A plant on the device:")
    for name, cfg in (("plate", {"nodes": [256, 256]}), ("block", {"nodes": [100, 100, 100]})):
        cpu = make_plant(name, cfg)
        dp = on_device(cpu, "cuda", xp=xp)
        X = dp.to_device(cpu.initial_state(4))
        u = np.full(cpu.n_u, 0.05)

        def first(dp=dp, X=X, u=u):
            dp.step_resident(X, u)
            synchronize(xp)
        check(f"{name} {cfg['nodes']}: first step, 4 runs (kernel compilation)", first)

        def later(dp=dp, X=X, u=u, cpu=cpu):
            t0 = time.perf_counter()
            for _ in range(3):
                dp.step_resident(X, u)
            synchronize(xp)
            ns = (time.perf_counter() - t0) / (3 * 4 * cpu.n_x) * 1e9
            return f"{ns:.2f} ns/node-step resident; memory plan: {device_runs_per_batch(dp)} runs per batch"
        check(f"{name} {cfg['nodes']}: later steps", later)

    if not args.skip_design:
        print("A small design and Monte Carlo, CPU vs device (tests/test_device.py's check, on this device):")
        check("design + Monte Carlo equal the CPU's", lambda: small_design(xp))
    return 0


def small_design(xp) -> str:
    import numpy as np

    from core_helpers import coarse_scenario
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_control.evaluation.montecarlo import simulate
    from sep_plant.device import on_device

    s = coarse_scenario(20, 40)
    st = DesignSettings(p=5, q=5, n_r=8, ensemble=20)
    a = run_design(s.plant, s.problem, st, show_progress=False, log=lambda m: None)
    dev = on_device(s.plant, "cuda", xp=xp)
    b = run_design(dev, s.problem, st, show_progress=False, log=lambda m: None)
    ja, jb = a.meta["optimizer"]["nominal_cost"], b.meta["optimizer"]["nominal_cost"]
    du = float(np.max(np.abs(a.nominal.u - b.nominal.u)) / np.max(np.abs(a.nominal.u)))
    ma = simulate(s.plant, a, "rom_lqg", 0, 30).metrics()
    mb = simulate(dev, a, "rom_lqg", 0, 30).metrics()
    dm = max(abs(ma[k] - mb[k]) / max(1.0, abs(ma[k])) for k in ("cost_mean", "cost_std", "in_band", "rms"))
    verdict = "EQUAL" if abs(ja - jb) <= 1e-10 * ja and du <= 1e-6 and dm <= 1e-10 else "DIFFERENT"
    return (f"{verdict}: nominal cost rel. diff {abs(ja - jb) / ja:.1e} (<= 1e-10), inputs {du:.1e} (<= 1e-6), "
            f"Monte Carlo metrics {dm:.1e} (<= 1e-10); device moved {dev.stats.to_device / 1e6:.1f} MB up, "
            f"{dev.stats.to_host / 1e6:.1f} MB down over {dev.stats.run_steps} run-steps")


if __name__ == "__main__":
    sys.exit(main())
