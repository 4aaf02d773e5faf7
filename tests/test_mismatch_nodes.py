"""The sim-to-real rehearsal over topics: the controllers refuse a plant that differs from the
design's model unless allow_model_mismatch:=true, then run, log the differences and report them
on /diagnostics and in their summaries; the plant node's perturbation parameters; lockstep against
a truth plant (a scenario_file with a biased key, and a perturbation) equals the offline
`evaluate --truth/--perturb` run of the same seed and run to 1e-9."""
import json

import numpy as np
import pytest

from node_harness import field_matrix, joint_matrix, launcher, probe, small_case, SMALL, wait_for_episode  # noqa: F401
from sep_control.evaluation.montecarlo import simulate
from sep_plant.ros import contract as c
from sep_plant.scenario import scenario_payload
from sep_plant.truth import truth_plant

pytestmark = pytest.mark.ros

TOPICS = (c.FIELD, c.FIELD_ESTIMATE, c.APPLIED_INPUT, c.MEASUREMENTS)
BIAS = [0.3, -0.2, 0.1, 0.0, 0.25]
PERTURBATION = {'input_gain': 0.8, 'sensor_bias': BIAS}
EXPECTED = ['plant.t_right: 150.0 -> 147.0', 'input_gain: 0.8', 'sensor_bias: [0.3, -0.2, 0.1, 0, 0.25]']


@pytest.fixture(scope='module')
def truth_file(tmp_path_factory):
    """The small case's scenario with the right boundary held 3 degrees colder."""
    import yaml

    f = tmp_path_factory.mktemp('truth') / 'truth.yaml'
    f.write_text(yaml.safe_dump({**SMALL, 't_right': 147.0}))
    return f


def truth_of(case):
    return truth_plant(case.design.scenario, {'t_right': 147.0}, PERTURBATION)


@pytest.mark.parametrize('perturbed', [False, True], ids=['plant_key', 'perturbation'])
def test_controllers_refuse_a_truth_unless_allowed(launcher, probe, small_case, perturbed):
    pr = probe()
    s = small_case.design.scenario
    scen = s.with_plant(t_right=147.0) if not perturbed else s
    pert = {'input_gain': [0.8] * 5} if perturbed else None
    pr.publish(c.SCENARIO, c.scenario_msg(scenario_payload(scen, s.info, pert)))
    p = launcher.start('lqg', params={'design_file': small_case.design_file, 'wait_for_scenario_s': 20.0})
    assert p.wait(30) == 2, p.output()
    out = p.output()
    what = 'input_gain: 0.8' if perturbed else 'plant.t_right: 150.0 != 147.0'
    assert what in out and 'allow_model_mismatch:=true' in out, out


def test_allowed_mismatch_still_refuses_another_problem(launcher, probe, small_case):
    pr = probe()
    s = small_case.design.scenario
    pr.publish(c.SCENARIO, c.scenario_msg(scenario_payload(s.with_plant(t_right=147.0).replace(band=2.0), s.info)))
    p = launcher.start('lqg', params={'design_file': small_case.design_file, 'wait_for_scenario_s': 20.0,
                                      'allow_model_mismatch': True})
    assert p.wait(30) == 2, p.output()
    assert 'even with allow_model_mismatch' in p.output() and 'problem.band' in p.output()


def run_rehearsal(launcher, probe, case, truth_file, tmp_path, *, three: bool, seed: int, run: int):
    pr = probe().subscribe(*TOPICS, c.DIAGNOSTICS)
    ctl = {'design_file': case.design_file, 'wait_for_scenario_s': 20.0, 'allow_model_mismatch': True}
    if three:
        est = launcher.start('estimator', params={**ctl, 'summary_file': tmp_path / 'est.json'})
        lqr = launcher.start('lqr', params={**ctl, 'summary_file': tmp_path / 'lqr.json'})
        controllers, subscribers = [est, lqr], 3
    else:
        controllers = [launcher.start('lqg', params={**ctl, 'summary_file': tmp_path / 'lqg.json'})]
        subscribers = 2
    # both controller nodes' /diagnostics writers seen before the (fast) episode: a controller
    # exits at its end, and a status it wrote before the probe matched it would be lost
    pr.wait_for(lambda: pr.subs[c.DIAGNOSTICS].get_publisher_count() >= 2, 20, 'controller diagnostics publishers')
    pr.wait_matched(subs=(c.FIELD_ESTIMATE,))
    plant = launcher.start('plant', params={
        'scenario_file': truth_file, 'seed': seed, 'run': run, 'input_gain': 0.8,
        'sensor_bias': '[' + ', '.join(str(b) for b in BIAS) + ']', 'wait_for_subscribers': subscribers,
        'wait_for_field_subscribers': 1, 'summary_file': tmp_path / 'plant.json', 'command_timeout_s': 20.0})
    wait_for_episode(pr, plant, controllers, case)
    return pr, controllers, json.loads((tmp_path / 'plant.json').read_text())


@pytest.mark.parametrize('three', [False, True], ids=['plant+lqg', 'plant+estimator+lqr'])
def test_lockstep_against_a_truth_equals_offline(launcher, probe, small_case, truth_file, tmp_path, three):
    seed, run = 7, 2
    pr, controllers, plant_summary = run_rehearsal(launcher, probe, small_case, truth_file, tmp_path,
                                                   three=three, seed=seed, run=run)
    assert plant_summary['status'] == 'completed'
    assert plant_summary['perturbation'] == {'input_gain': [0.8] * 5, 'sensor_bias': BIAS}
    d, dt, N = small_case.design, small_case.dt, small_case.n_steps
    ref = simulate(truth_of(small_case).plant, d, 'rom_lqg', seed, range(run, run + 1))
    F = field_matrix(pr, c.FIELD, dt, N, column=3)
    F_hat = field_matrix(pr, c.FIELD_ESTIMATE, dt, N, column=3)
    U = joint_matrix(pr, c.APPLIED_INPUT, dt, N, 'effort')
    Y = joint_matrix(pr, c.MEASUREMENTS, dt, N + 1, 'position')
    for got, want in ((F, ref.F[0]), (F_hat, ref.F_hat[0]), (U, ref.U[0]), (Y, ref.Y[0])):
        assert np.max(np.abs(got - want)) <= 1e-9
    # ... and it is not the model's episode (the truth is felt)
    assert np.max(np.abs(F - simulate(small_case.plant, d, 'rom_lqg', seed, range(run, run + 1)).F[0])) > 0.1
    if three:
        summaries = [json.loads((tmp_path / f).read_text()) for f in ('est.json', 'lqr.json')]
    else:
        lqg = json.loads((tmp_path / 'lqg.json').read_text())
        summaries = [lqg['estimator'], lqg['lqr']]
    for s in summaries:
        assert s['model_mismatch'] == EXPECTED, s
    for p in controllers:
        assert 'model mismatch (allow_model_mismatch)' in p.output() and 'plant.t_right: 150.0 -> 147.0' in p.output()
        # the closing summary line names the mismatch too
        assert '; model mismatch: ' + '; '.join(EXPECTED) in p.output(), p.output()
    pr.wait_for(lambda: pr.diagnostics('lqr') and pr.diagnostics('estimator'), 10, 'controller diagnostics')
    for name in ('lqr', 'estimator'):
        assert json.loads(pr.diagnostics(name)[-1]['model_mismatch']) == EXPECTED
    assert json.loads(pr.diagnostics('plant')[-1]['perturbation']) == plant_summary['perturbation']


@pytest.mark.parametrize('params,expect', [
    ({'input_offset': '[0.1, 0.2]'}, 'bad parameter input_offset: input_offset must be a number or a list of 5'),
    ({'sensor_bias': 'abc'}, 'bad parameter sensor_bias'),
])
def test_plant_refuses_a_bad_perturbation_parameter(launcher, small_case, params, expect):
    p = launcher.start('plant', params={'scenario_file': small_case.scenario_file, **params,
                                        'wait_for_subscribers': 0})
    assert p.wait(30) == 2, p.output()
    assert expect in p.output(), p.output()


def test_plant_integer_perturbation_values_are_numbers(launcher, small_case, tmp_path):
    p = launcher.start('plant', params={'scenario_file': small_case.scenario_file, 'input_gain': 1,
                                        'input_offset': '[0, 0, 1, 0, 0]', 'wait_for_subscribers': 0,
                                        'summary_file': tmp_path / 'p.json', 'command_timeout_s': 0.2})
    p.wait(30)
    assert 'perturbed: PerturbedPlant(slab' in p.output(), p.output()
    assert json.loads((tmp_path / 'p.json').read_text())['perturbation'] == {'input_offset': [0, 0, 1.0, 0, 0]}
