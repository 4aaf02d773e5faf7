"""Acceptance: a lockstep closed-loop episode over topics reproduces the offline closed-loop
simulation (`sep_control.evaluation.montecarlo.simulate`, same seed and run) to 1e-9 F over the whole
trajectory, and its state estimates (the ROM state and the disturbance estimates) the offline
filter's; plant + lqg (two processes) and plant + estimator + lqr (three processes), for designs
with input disturbance states (the default), output ones, and none; and for the field-weighted
LQR (lqr_weighting: field) with noise-kind disturbance states on a slab whose process noise has
channels of its own, and with the combination noise+output there (three processes)."""
import json

import numpy as np
import pytest

from node_harness import (SMALL, _cached_case, field_matrix, joint_matrix, launcher, probe, reference_case,  # noqa: F401
                          small_case, wait_for_episode)
from sep_control.evaluation.montecarlo import simulate
from sep_estimator.tvkf import KalmanFilter
from sep_plant.ros import contract as c
from ros_helpers import parse_field_cloud

pytestmark = pytest.mark.ros

TOPICS = (c.FIELD, c.FIELD_ESTIMATE, c.APPLIED_INPUT, c.COMMAND, c.MEASUREMENTS, c.STATE_ESTIMATE)


@pytest.fixture(scope='session')
def small_kind_case(tmp_path_factory, request):
    """The small scenario designed with disturbance states of another kind (output, none)."""
    kind = request.param
    return _cached_case(tmp_path_factory, f'small_{kind}', settings={'disturbance': kind}, **SMALL)


FIELD_NOISE_YAML = """\
plant: {type: slab, n_x: 20, noise_centers: [0.25, 0.75], noise_sigma: 0.2, sensor_positions: [0.2, 0.5, 0.8]}
n_steps: 40
band_window: [24, 40]
lqr_k_switch: 20
lqr_weighting: field
"""


@pytest.fixture(scope='session')
def field_noise_case(tmp_path_factory):
    """A small slab with its own noise channels, the field weighting and the noise kind."""
    return _cached_case(tmp_path_factory, 'small_field_noise', yaml_text=FIELD_NOISE_YAML,
                        settings={'disturbance': 'noise'})


def run_episode(launcher, probe, case, tmp_path, *, three: bool, seed: int, run: int,
                mode: str = 'lockstep', rtf: float = 10.0, field_subscribers: int = 1):
    pr = probe().subscribe(*TOPICS, c.DIAGNOSTICS)
    ctl = {'design_file': case.design_file, 'wait_for_scenario_s': 20.0}
    if three:
        est = launcher.start('estimator', params={**ctl, 'summary_file': tmp_path / 'est.json'})
        lqr = launcher.start('lqr', params={**ctl, 'summary_file': tmp_path / 'lqr.json'})
        controllers = [est, lqr]
        subscribers = 3   # estimator, lqr (its watchdog), probe
    else:
        controllers = [launcher.start('lqg', params={**ctl, 'summary_file': tmp_path / 'lqg.json'})]
        subscribers = 2
    pr.wait_matched(subs=(c.FIELD_ESTIMATE, c.STATE_ESTIMATE, c.COMMAND))
    plant = launcher.start('plant', params={
        'scenario_file': case.scenario_file, 'seed': seed, 'run': run, 'mode': mode,
        'real_time_factor': rtf, 'wait_for_subscribers': subscribers,
        'wait_for_field_subscribers': field_subscribers, 'summary_file': tmp_path / 'plant.json',
        'command_timeout_s': 20.0})
    wait_for_episode(pr, plant, controllers, case)
    summary = json.loads((tmp_path / 'plant.json').read_text())
    return pr, summary


def check_equivalence(pr, case, seed, run):
    """The topics equal the offline closed loop (`simulate`, same seed and run) to 1e-9."""
    d, dt, N = case.design, case.dt, case.n_steps
    ref = simulate(case.plant, d, 'rom_lqg', seed, range(run, run + 1))
    F = field_matrix(pr, c.FIELD, dt, N, column=3)
    F_hat = field_matrix(pr, c.FIELD_ESTIMATE, dt, N, column=3)
    F_std = field_matrix(pr, c.FIELD_ESTIMATE, dt, N, column=4)
    U = joint_matrix(pr, c.APPLIED_INPUT, dt, N, 'effort')
    Y = joint_matrix(pr, c.MEASUREMENTS, dt, N + 1, 'position')
    err = np.max(np.abs(F - ref.F[0]))
    assert err <= 1e-9, f'max |f_topics - f_offline| = {err:.3e}'
    assert np.max(np.abs(U - ref.U[0])) <= 1e-9
    assert np.max(np.abs(Y - ref.Y[0])) <= 1e-9
    assert np.max(np.abs(F_hat - ref.F_hat[0])) <= 1e-9
    assert np.max(np.abs(F_std - ref.F_std)) <= 1e-9
    # the state estimates z_k = [a_k; d_k], named a_0.., d_0.., are the offline filter's on the same data
    Z = joint_matrix(pr, c.STATE_ESTIMATE, dt, N + 1, 'position')
    assert list(pr.by_step(c.STATE_ESTIMATE, dt)[N].name) == c.state_labels(d.n_r, d.lqg.n_d)
    kf = KalmanFilter(d.lqg)
    for k in range(N + 1):
        z = kf.update(k, ref.Y[0, k] - d.nominal.y[k])[0]
        assert np.max(np.abs(Z[k] - z)) <= 1e-9, k
        if k < N:
            kf.predict(k, ref.U[0, k] - d.nominal.u[k])
    # the clouds carry the plant's node coordinates
    cloud = pr.by_step(c.FIELD, dt)[0]
    xyz = np.stack([parse_field_cloud(cloud)[k] for k in ('x', 'y', 'z')], axis=1)
    np.testing.assert_array_equal(xyz, d.field_xyz)
    return err


@pytest.mark.parametrize('three', [False, True], ids=['plant+lqg', 'plant+estimator+lqr'])
def test_lockstep_equivalence_small(launcher, probe, small_case, tmp_path, three):
    assert small_case.design.disturbance.kind == 'input' and small_case.design.lqg.n_d == 5
    pr, summary = run_episode(launcher, probe, small_case, tmp_path, three=three, seed=7, run=3)
    assert summary['status'] == 'completed' and summary['steps'] == small_case.n_steps
    assert summary['deadline_misses'] == 0 and summary['rejected_messages'] == 0
    check_equivalence(pr, small_case, 7, 3)
    if three:
        lqr = json.loads((tmp_path / 'lqr.json').read_text())
        assert lqr['fallbacks'] == 0 and lqr['commands'] == small_case.n_steps


def test_lockstep_equivalence_reference(launcher, probe, reference_case, tmp_path):
    pr, summary = run_episode(launcher, probe, reference_case, tmp_path, three=False, seed=0, run=5)
    assert summary['steps'] == 250
    check_equivalence(pr, reference_case, 0, 5)
    lqg = json.loads((tmp_path / 'lqg.json').read_text())
    assert lqg['estimator']['updates'] == 251 and lqg['estimator']['nis_consistent'] in (True, None)
    assert lqg['estimator']['state_estimates_published'] == 251      # the probe subscribes to them


@pytest.mark.parametrize('small_kind_case', ['output', 'none'], indirect=True)
def test_lockstep_equivalence_disturbance_kinds(launcher, probe, small_kind_case, tmp_path):
    case = small_kind_case
    kind = case.design.disturbance.kind if case.design.disturbance is not None else 'none'
    assert kind == case.design.meta['settings']['disturbance']
    pr, summary = run_episode(launcher, probe, case, tmp_path, three=False, seed=7, run=3)
    assert summary['status'] == 'completed' and summary['steps'] == case.n_steps
    check_equivalence(pr, case, 7, 3)


def test_lockstep_equivalence_field_weighting_and_noise_kind(launcher, probe, field_noise_case, tmp_path):
    case = field_noise_case
    assert case.design.disturbance.kind == 'noise' and case.design.problem.lqr_weighting == 'field'
    assert not case.design.info.noise_on_inputs
    pr, summary = run_episode(launcher, probe, case, tmp_path, three=False, seed=7, run=3)
    assert summary['status'] == 'completed' and summary['steps'] == case.n_steps
    check_equivalence(pr, case, 7, 3)


@pytest.fixture(scope='session')
def combined_case(tmp_path_factory):
    """The small slab with its own noise channels and a combination of disturbance kinds:
    noise+output (stacked states, the noise part acted on, the sensor-bias part not)."""
    return _cached_case(tmp_path_factory, 'small_noise_output', yaml_text=FIELD_NOISE_YAML,
                        settings={'disturbance': 'noise+output'})


def test_lockstep_equivalence_combined_disturbance_kinds(launcher, probe, combined_case, tmp_path):
    case = combined_case
    dist = case.design.disturbance
    assert dist.kind == 'noise+output' and dist.part_dims == (2, 1)
    pr, summary = run_episode(launcher, probe, case, tmp_path, three=True, seed=7, run=3)
    assert summary['status'] == 'completed' and summary['steps'] == case.n_steps
    check_equivalence(pr, case, 7, 3)
