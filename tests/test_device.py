"""`--device cuda` without a GPU: the built-in plants, the design and the Monte Carlo stepped on
an emulated device (`device_guard`: numpy underneath, as strict as CuPy at the host/device
boundary), parallel cyclic reduction against LAPACK, and the errors a user without CuPy, or with
a CPU-only plant, sees."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import lapack

from core_helpers import coarse_scenario, one_blas_thread  # noqa: F401 (fixture)
from device_guard import GuardArray, HostDeviceMix, guard
from sep_plant.conformance import check_plant
from sep_plant.device import DeviceError, DevicePlant, array_module, base_plant, on_device
from sep_plant.plants import adi, make_plant, type_name_of
from sep_plant.plants.backend import namespace, to_host

PLANTS = {
    "slab": {"n_x": 40},
    "plate": {"nodes": [12, 9]},
    "block": {"nodes": [6, 5, 4], "radiation": 1e-9, "unit": "K", "t_init": 400.0, "t_amb": 300.0,
              "boundary_temperatures": {"z_min": 450.0}},
    "allen_cahn": {"nodes": [10, 8]},
}


def _cupy_usable() -> bool:
    try:
        array_module("cuda")
    except DeviceError:
        return False
    return True


# ------------------------------------------------------------------------------ the emulator itself
def test_the_emulated_device_refuses_what_cupy_refuses():
    d = guard.asarray(np.arange(6.0).reshape(2, 3))
    assert namespace(d) is guard and isinstance(d * 2.0 + d, GuardArray)
    with pytest.raises(HostDeviceMix):
        np.asarray(d)                                  # implicit download
    with pytest.raises(HostDeviceMix):
        d * np.ones(3)                                 # host operand
    host = np.zeros((2, 3))
    with pytest.raises(HostDeviceMix):
        host[:] = d
    with pytest.raises(HostDeviceMix):
        d[:] = host                                    # implicit upload
    with pytest.raises((HostDeviceMix, TypeError, ValueError)):
        lapack.dptsv(d[0], d[0, :2], d[0])             # LAPACK runs on host arrays only
    assert np.array_equal(to_host(d[:, np.array([0, 2])]), [[0.0, 2.0], [3.0, 5.0]])   # host indices: fine


# ------------------------------------------------------------------------------ line solves
@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 33, 100])
def test_parallel_cyclic_reduction_solves_what_lapack_solves(n):
    rng = np.random.default_rng(n)
    M = 7
    sub, sup = -rng.uniform(0.1, 1.0, (M, n)), -rng.uniform(0.1, 1.0, (M, n))
    diag = np.abs(sub) + np.abs(sup) + rng.uniform(0.01, 1.0, (M, n))        # diagonally dominant
    rhs = rng.standard_normal((M, n))
    keep = [a.copy() for a in (sub, diag, sup, rhs)]
    x = adi.solve_pcr(sub, diag, sup, rhs)
    for a, b in zip(keep, (sub, diag, sup, rhs)):
        assert np.array_equal(a, b)                                           # inputs untouched
    for m in range(M if n > 1 else 0):
        dl, du = sub[m, 1:].copy(), sup[m, :-1].copy()
        *_, ref, info = lapack.dgtsv(dl, diag[m].copy(), du, rhs[m].copy())
        assert info == 0
        np.testing.assert_allclose(x[m], ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))
    if n == 1:
        np.testing.assert_allclose(x, rhs / diag, rtol=1e-15)
    xd = adi.solve_pcr(*(guard.asarray(a) for a in (sub, diag, sup, rhs)))
    assert isinstance(xd, GuardArray) and np.array_equal(to_host(xd), x)


def test_parallel_cyclic_reduction_refuses_non_finite_input():
    diag, off, rhs = np.full((2, 6), 4.0), np.full((2, 6), -1.0), np.ones((2, 6))
    rhs[1, 3] = np.nan
    with pytest.raises(FloatingPointError, match="non-finite"):
        adi.solve_pcr(off, diag, off, rhs)


# ------------------------------------------------------------------------------ plants
@pytest.mark.parametrize("name", sorted(PLANTS))
def test_built_in_plants_step_on_the_device_as_on_the_cpu(name):
    """A batch, inputs given once for every run, noise: the device step equals the CPU step to
    round-off and never crosses to the host on its own; the wrapped plant conforms."""
    cpu = make_plant(name, PLANTS[name])
    dev = on_device(cpu, "cuda", xp=guard)
    assert isinstance(dev, DevicePlant) and base_plant(dev) is not cpu and type_name_of(dev) == name
    rng = np.random.default_rng(1)
    X = cpu.initial_state(5) + rng.normal(0.0, 0.2, (5, cpu.n_x))
    U = rng.normal(0.05, 0.02, (5, cpu.n_u))
    W = rng.normal(0.0, 0.02, (5, cpu.n_u))
    for args in ((X, U, W), (X, U[0]), (X[0], U[0])):
        ref = cpu.step(*args)
        got = dev.step(*args)
        assert type(got) is np.ndarray and got.shape == ref.shape
        scale = np.max(np.abs(ref - args[0]))
        assert np.max(np.abs(got - ref)) <= 1e-11 * scale
    resident = dev.plant.step(guard.asarray(X), guard.asarray(U))             # what stays on the device
    assert isinstance(resident, GuardArray)
    check_plant(dev, np.full(cpu.n_u, 0.05))
    np.testing.assert_array_equal(dev.observe(X), cpu.observe(X))
    assert dev.n_x == cpu.n_x and dev.config() == cpu.config()


def test_a_device_batch_goes_to_the_device_a_block_at_a_time():
    """The GPU holds one block, whatever the batch: the same result, one download per block."""
    import pickle

    from sep_plant.device import DEVICE_BLOCK_NODES

    cpu = make_plant("plate", PLANTS["plate"])
    dev = DevicePlant(cpu, guard, "cuda")
    assert dev.plant.block_nodes == DEVICE_BLOCK_NODES and cpu.block_nodes < DEVICE_BLOCK_NODES
    small = DevicePlant(cpu, guard, "cuda", block_nodes=2 * cpu.n_x)         # 2 runs per block
    rng = np.random.default_rng(2)
    X = cpu.initial_state(5) + rng.normal(0.0, 0.2, (5, cpu.n_x))
    U, W = np.full((5, cpu.n_u), 0.05), rng.normal(0.0, 0.02, (5, cpu.n_u))
    before = guard.transfers["to_host"]
    got = small.step(X, U[0], W)
    assert guard.transfers["to_host"] - before == 3                           # blocks of 2, 2, 1 runs
    np.testing.assert_allclose(got, dev.step(X, U, W), rtol=0, atol=1e-12)
    np.testing.assert_allclose(got, cpu.step(X, U, W), rtol=0, atol=1e-11 * np.max(np.abs(got - X)))
    small.solver = "thomas"                                                   # the plant's attribute
    assert small.plant.solver == "thomas" and cpu.solver == "auto"
    np.testing.assert_allclose(small.step(X, U, W), got, rtol=0, atol=1e-12)  # Thomas on the device too
    with pytest.raises(ValueError, match="block_nodes"):
        DevicePlant(cpu, guard, "cuda", block_nodes=0)
    if not _cupy_usable():                                                    # unpickled: rebuilt on its device
        with pytest.raises(DeviceError, match="--device cuda"):
            pickle.loads(pickle.dumps(small))


def test_a_cpu_only_plant_is_refused_with_what_to_do():
    from broken_plants import ToyPlant

    with pytest.raises(DeviceError, match="device_capable"):
        on_device(ToyPlant(), "cuda", xp=guard)
    assert on_device(ToyPlant(), "cpu").__class__ is ToyPlant                   # cpu: the plant itself


def test_a_plant_that_claims_the_device_but_breaks_there_fails_the_conformance_check():
    """What `design --device cuda` runs before any work (cli_common.plant_or_exit)."""
    from broken_plants import ToyPlant
    from sep_plant.protocol import PlantError

    class Claims(ToyPlant):
        device_capable = True                   # but its step mixes host arrays into device ones

    Claims.__module__ = ToyPlant.__module__
    check_plant(Claims())                                                     # fine on the CPU
    with pytest.raises(PlantError, match="step"):
        check_plant(on_device(Claims(), "cuda", xp=guard))


# ------------------------------------------------------------------------------ the whole design
def test_design_and_monte_carlo_on_the_device_equal_the_cpu_ones(one_blas_thread):
    """Every plant step of the design (sensitivity and TV-ERA experiments, EnKF belief, rollouts)
    and of the Monte Carlo through the emulated device: the same design to round-off."""
    from sep_control.design.pipeline import DesignSettings, run_design
    from sep_control.evaluation.montecarlo import simulate

    s = coarse_scenario(20, 40)
    st = DesignSettings(p=5, q=5, n_r=8, ensemble=20)
    a = run_design(s.plant, s.problem, st, show_progress=False, log=lambda m: None)
    dev = on_device(s.plant, "cuda", xp=guard)
    before = guard.transfers["to_host"]
    b = run_design(dev, s.problem, st, show_progress=False, log=lambda m: None)
    assert guard.transfers["to_host"] - before > s.problem.n_steps        # the steps did run on the device
    ja, jb = a.meta["optimizer"]["nominal_cost"], b.meta["optimizer"]["nominal_cost"]
    assert abs(ja - jb) <= 1e-10 * ja
    assert np.max(np.abs(a.nominal.u - b.nominal.u)) <= 1e-6 * np.max(np.abs(a.nominal.u))
    assert b.scenario == a.scenario                                       # the file names the plant, not the device
    ma = simulate(s.plant, a, "rom_lqg", 0, 30).metrics()
    mb = simulate(dev, a, "rom_lqg", 0, 30).metrics()
    for key in ("cost_mean", "cost_std", "in_band", "rms"):
        assert abs(ma[key] - mb[key]) <= 1e-10 * max(1.0, abs(ma[key])), key


def test_dask_workers_rebuild_the_plant_on_its_device():
    from sep_control.compute.engine import plant_spec, worker_plant

    cpu = make_plant("slab", PLANTS["slab"])
    dev = DevicePlant(cpu, guard, "cuda")
    spec = plant_spec(dev)
    assert spec[0] == "slab" and spec[2] == "cuda" and plant_spec(cpu)[2] == "cpu"
    assert worker_plant(plant_spec(cpu)).config() == cpu.config()


# ------------------------------------------------------------------------------ the command line
@pytest.mark.skipif(_cupy_usable(), reason="CuPy and a GPU are present: the refusal cannot be shown")
def test_device_cuda_without_cupy_or_gpu_exits_2_saying_what_to_install(tmp_path, capsys):
    from sep_control.cli.design import main

    with pytest.raises(SystemExit) as exc:
        main(["--out", str(tmp_path / "d.npz"), "--device", "cuda", "--quiet"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--device cuda" in err and ("CuPy" in err or "cupy" in err)
    assert not (tmp_path / "d.npz").exists()


# ------------------------------------------------------------------------------ resident experiments
def test_the_design_keeps_its_experiments_on_the_device(one_blas_thread):
    """The experiment batches stay on the device: what crosses is a small fraction of what a
    round trip of every state would move, and every run-step is counted."""
    from sep_control.design.pipeline import DesignSettings, run_design

    s = coarse_scenario(300, 40)
    dev = on_device(s.plant, "cuda", xp=guard)
    # plan 0.8's experiment batches (the figures below were measured on them)
    run_design(dev, s.problem, DesignSettings(p=5, q=5, n_r=8, ensemble=20, experiment_plan="0.8"),
               show_progress=False, log=lambda m: None)
    st = dev.stats
    round_trip = 2 * 8 * st.run_steps * s.plant.n_x            # every state up and down, every step
    assert st.run_steps > 10_000
    # what does cross is O(N n_x) per experiment batch, not O(runs N n_x): the nominal rollouts'
    # states (the design keeps them on the host), the nominal states a batch starts from, the
    # EnKF's field mean and std per step, the field bases once per identification (8 % here)
    assert st.to_device + st.to_host < 0.12 * round_trip


def test_the_device_memory_plan_sizes_batches_from_device_memory():
    from sep_plant.device import (DEVICE_BLOCK_BYTES_PER_NODE, DEVICE_MEMORY_SHARE, DEVICE_RUN_COPIES,
                                  EMULATED_DEVICE_MEMORY, device_memory, device_runs_per_batch)

    dev = on_device(make_plant("plate", {"nodes": [64, 64]}), "cuda", xp=guard)
    assert device_memory(guard) == EMULATED_DEVICE_MEMORY
    expect = (int(DEVICE_MEMORY_SHARE * EMULATED_DEVICE_MEMORY) - dev.block_nodes * DEVICE_BLOCK_BYTES_PER_NODE) \
        // (8 * DEVICE_RUN_COPIES * dev.n_x)
    assert device_runs_per_batch(dev) == expect > 1000


def test_a_non_finite_device_state_is_caught_without_a_check_per_line_solve(one_blas_thread):
    """A device line solve does not synchronize to check its result; the round trip step, the
    sensitivity pass and the EnKF check what comes back instead."""
    from sep_control.design.belief import objective_of, run_belief
    from sep_control.design.linearization import sensitivity_normal_equations
    from sep_plant.protocol import nominal_states

    s = coarse_scenario(20, 12)
    dev = on_device(s.plant, "cuda", xp=guard)
    X = s.plant.initial_state(3)
    X[1, 4] = np.nan
    resident = dev.step_resident(dev.to_device(X), np.full(dev.n_u, 0.1))    # no check, no host sync
    assert not np.isfinite(to_host(resident)).all()
    with pytest.raises(FloatingPointError, match="non-finite"):
        dev.step(X, np.full(dev.n_u, 0.1))
    U = s.problem.u_start(dev.n_u)
    Xbar = nominal_states(s.plant, U)
    Xbar[3, 2] = np.nan
    with pytest.raises(FloatingPointError, match="non-finite"):
        sensitivity_normal_equations(dev, U, Xbar, objective_of(dev, s.problem))
    U[2] = np.nan
    with pytest.raises(FloatingPointError, match="non-finite"):
        run_belief(dev, U, s.problem, 8, 0, X=Xbar * 0 + s.plant.initial_state(1))


@pytest.mark.parametrize("method", ["gram", "svd"])
def test_the_field_basis_on_the_device_equals_the_hosts(method):
    """`IncrementalBasis` with its Phi on the device (Gram matrices and CholeskyQR2 there, or
    0.8.0's SVD through a QR): the same rank and span, coefficients that rebuild the snapshots to
    round-off; `merge` too."""
    from sep_control.design.basis import IncrementalBasis

    rng = np.random.default_rng(3)
    n = 500
    modes = np.linalg.qr(rng.standard_normal((n, 12)))[0] * np.logspace(0, -6, 12)
    blocks = [rng.standard_normal((9, 12)) @ modes.T for _ in range(5)]
    host, dev = IncrementalBasis(n, 1e-8, method=method), IncrementalBasis(n, 1e-8, xp=guard, method=method)
    for D in blocks:
        ch = host.add(D)
        cd = dev.add(guard.asarray(D))
        assert isinstance(cd, GuardArray) and cd.shape == ch.shape
        np.testing.assert_allclose(to_host(cd) @ to_host(dev.phi).T, D, rtol=0, atol=1e-10 * np.abs(D).max())
    assert dev.rank == host.rank == 12
    P_h, P_d = host.phi @ host.phi.T, to_host(dev.phi) @ to_host(dev.phi).T
    np.testing.assert_allclose(P_d, P_h, rtol=0, atol=1e-9)
    other = np.linalg.qr(rng.standard_normal((n, 4)))[0]
    coef = rng.standard_normal((4, 20))
    host.merge(other, coef)
    dev.merge(guard.asarray(other), coef)
    assert dev.rank == host.rank == 16
    np.testing.assert_allclose(to_host(dev.phi).T @ to_host(dev.phi), np.eye(16), rtol=0, atol=1e-12)
