"""The estimator's episode logic without ROS (sep_estimator.estimator_core): what real message
streams need on top of the Kalman filter — order checks, gaps, restarts, late inputs, NIS —
against a plain KalmanFilter driven by hand, on the coarse slab design."""
import numpy as np
import pytest

from core_helpers import cached_design, coarse_scenario
from sep_estimator.estimator_core import EstimatorCore
from sep_estimator.tvkf import KalmanFilter
from sep_plant import gate


@pytest.fixture(scope="module")
def design():
    return cached_design(coarse_scenario(20, 40), p=5, q=5, n_r=10, ensemble=20, belief=False)


def core_of(d):
    return EstimatorCore(d.lqg, d.nominal.u, d.nominal.y, d.nominal.field)


def data(d, seed=0):
    rng = np.random.default_rng(seed)
    N = d.n_steps
    return d.nominal.y + rng.normal(0, 1, (N + 1, d.info.n_y)), d.nominal.u + rng.normal(0, 0.05, (N, d.info.n_u))


def test_in_order_stream_is_the_kalman_filter(design):
    d = design
    y, u = data(d)
    core, kf = core_of(d), KalmanFilter(d.lqg)
    for k in range(d.n_steps + 1):
        a, rej = core.measurement(k, y[k])
        assert rej is None
        np.testing.assert_allclose(a, kf.update(k, y[k] - d.nominal.y[k])[0], rtol=0, atol=1e-12)
        f, std = core.field_estimate()
        np.testing.assert_allclose(f, d.nominal.field[k] + kf.field_deviation()[0], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(std, d.lqg.field_std[k])
        if k < d.n_steps:
            assert core.applied(k, u[k]) is None
            kf.predict(k, u[k] - d.nominal.u[k])
    assert core.counters()["updates"] == d.n_steps + 1 and core.counters()["input_source"]["applied"] == d.n_steps


def test_float32_field_reconstruction_tracks_the_float64_one(design):
    """field_precision 'float32' changes only the reconstruction's round-off (the estimate, the
    std and everything else are the same numbers)."""
    d = design
    y, u = data(d, 2)
    exact, single = core_of(d), EstimatorCore(d.lqg, d.nominal.u, d.nominal.y, d.nominal.field,
                                              field_precision="float32")
    for k in range(d.n_steps + 1):
        a64, _ = exact.measurement(k, y[k])
        a32, _ = single.measurement(k, y[k])
        np.testing.assert_array_equal(a32, a64)
        (f64, s64), (f32, s32) = exact.field_estimate(), single.field_estimate()
        dev = np.abs(f64 - d.nominal.field[k]).max()
        assert f32.dtype == np.float64 and np.abs(f32 - f64).max() <= 1e-6 * max(dev, 1e-12)
        np.testing.assert_array_equal(s32, s64)
        if k < d.n_steps:
            exact.applied(k, u[k])
            single.applied(k, u[k])
    with pytest.raises(ValueError, match="field precision"):
        EstimatorCore(d.lqg, d.nominal.u, d.nominal.y, d.nominal.field, field_precision="half")
    # the default 'auto' keeps this small basis in float64: the reconstruction is the float64 one
    auto = EstimatorCore(d.lqg, d.nominal.u, d.nominal.y, d.nominal.field)
    assert auto.field_precision == "float64" and exact.field_precision == "float64"
    assert single.field_precision == "float32"


def test_stale_and_duplicate_steps_are_refused_without_touching_the_filter(design):
    d = design
    y, u = data(d, 1)
    core = core_of(d)
    core.measurement(0, y[0])
    core.applied(0, u[0])
    core.measurement(1, y[1])
    before = core.estimate.copy()
    assert core.measurement(1, y[1])[1].category == gate.DUPLICATE
    assert core.measurement(0, y[0])[1].category == gate.STALE
    assert core.applied(0, u[0]).category == gate.DUPLICATE
    np.testing.assert_array_equal(core.estimate, before)


def test_gap_and_malformed_measurement_are_skipped(design):
    d = design
    y, u = data(d, 2)
    core, kf = core_of(d), KalmanFilter(d.lqg)
    core.measurement(0, y[0]); kf.update(0, y[0] - d.nominal.y[0])
    core.applied(0, u[0]); kf.predict(0, u[0] - d.nominal.u[0])
    # step 1 missing; step 2 arrives: skip 1, predict with the nominal (no input known), update 2
    a, _ = core.measurement(2, y[2])
    kf.skip(1); kf.predict(1, np.zeros(d.info.n_u)); kf.update(2, y[2] - d.nominal.y[2])
    np.testing.assert_allclose(a, kf.a[0], rtol=0, atol=1e-12)
    # step 3 malformed (y None): predicted, no update
    core.applied(2, u[2]); kf.predict(2, u[2] - d.nominal.u[2])
    a, _ = core.measurement(3, None)
    kf.skip(3)
    np.testing.assert_allclose(a, kf.a[0], rtol=0, atol=1e-12)
    c = core.counters()
    assert c["missing_measurements"] == 1 and c["skipped_updates"] == 1 and c["input_source"]["nominal"] == 1


def test_late_applied_input_is_corrected_exactly(design):
    """y_{k+1} before applied_input of step k: the filter predicts with the command; the applied
    input then differs (a limit clipped it): the estimate becomes exactly the one it would have
    been with the applied input in time."""
    d = design
    y, u = data(d, 3)
    late, ref = core_of(d), core_of(d)
    for k in range(5):
        for c in (late, ref):
            c.measurement(k, y[k])
        if k < 4:
            ref.applied(k, u[k])
            if k == 3:
                late.commanded(k, u[k] + 0.2)          # what the LQR asked for
            else:
                late.applied(k, u[k])
    assert not np.allclose(late.estimate, ref.estimate)
    # step 4 was processed with the command of step 3; now the applied input arrives (within step 4)
    late.applied(3, u[3])
    np.testing.assert_allclose(late.estimate, ref.estimate, rtol=0, atol=1e-12)
    assert late.counters()["late_inputs_corrected"] == 1 and late.counters()["input_source"]["commanded"] == 1
    # an applied input that comes after the following step cannot be corrected exactly: counted
    late.applied(4, u[4])
    late.measurement(5, y[5])
    late.commanded(5, u[5] + 0.3)
    late.measurement(6, y[6])      # predicted with the command of step 5
    late.measurement(7, y[7])      # and step 6 with the nominal (nothing known)
    late.applied(5, u[5])
    c = late.counters()
    assert c["late_inputs_uncorrected"] == 1 and c["late_inputs_corrected"] == 1
    assert c["input_source"] == {"applied": 4, "commanded": 2, "nominal": 1}


def test_join_mid_episode_restarts(design):
    d = design
    y, _ = data(d, 4)
    core = core_of(d)
    a, rej = core.measurement(12, y[12])
    assert rej is None and core.restarts == 1 and not core.kf.on_schedule
    ref = KalmanFilter(d.lqg)
    ref.restart_at(12)
    np.testing.assert_allclose(a, ref.update(12, y[12] - d.nominal.y[12])[0], rtol=0, atol=1e-12)


def test_nis_of_consistent_data_is_about_n_y(design):
    """Measurements generated by the filter's model itself (the ROM with its disturbance states,
    d_0 drawn from their prior) with the design's noise: the mean NIS is n_y (within its 99 %
    interval), and it is computed after the step (finish_step)."""
    d = design
    m, W, V = d.lqg.model, d.lqg.W, d.lqg.V
    assert d.lqg.n_d > 0 and m.n == d.n_r + d.lqg.n_d
    rng = np.random.default_rng(5)
    runs, nis = 40, []
    for _ in range(runs):
        core = core_of(d)
        a = rng.multivariate_normal(np.zeros(m.n), m.initial_covariance())
        for k in range(d.n_steps + 1):
            yk = d.nominal.y[k] + m.C[k] @ a + rng.multivariate_normal(np.zeros(d.info.n_y), V)
            core.measurement(k, yk)
            core.finish_step()
            if k < d.n_steps:
                core.applied(k, d.nominal.u[k])
                a = m.A[k] @ a + m.noise_input[k] @ rng.multivariate_normal(np.zeros(W.shape[0]), W)
        nis.append(core.nis_sum / core.nis_n)
    n_y = d.info.n_y
    lo, hi = gate.chi2_interval(n_y, runs * (d.n_steps + 1), 0.99)
    assert lo <= np.mean(nis) <= hi, (np.mean(nis), lo, hi)
    assert core.nis_stats()["nis_expected"] == n_y
