"""Acceptance: at real_time_factor 10 (a step every 25 ms) a full reference episode of
plant + lqg has zero deadline misses; with no miss the episode is the offline closed loop
for the same seed and run (so its in-band result is the offline Monte Carlo's)."""
import json

import numpy as np
import pytest

from node_harness import field_matrix, launcher, probe, reference_case  # noqa: F401
from sep_control import metrics
from sep_control.montecarlo import simulate
from sep_plant import contract as c

pytestmark = pytest.mark.ros


def test_realtime_rtf10_reference_episode_no_deadline_miss(launcher, probe, reference_case, tmp_path):
    case = reference_case
    dt, N = case.dt, case.n_steps
    pr = probe().subscribe(c.FIELD)
    lqg = launcher.start('lqg', params={'design_file': case.design_file, 'wait_for_scenario_s': 20.0,
                                        'summary_file': tmp_path / 'lqg.json'})
    pr.wait_for(lambda: 'estimator: design file' in lqg.output(), 30, 'lqg start')
    plant = launcher.start('plant', params={'scenario_file': case.scenario_file, 'mode': 'realtime',
                                            'real_time_factor': 10.0, 'seed': 4, 'run': 2,
                                            'wait_for_field_subscribers': 1,
                                            'summary_file': tmp_path / 'plant.json'})
    assert plant.wait(60) == 0, plant.output()
    assert lqg.wait(30) == 0, lqg.output()
    summ = json.loads((tmp_path / 'plant.json').read_text())
    print(json.dumps(summ, indent=1))
    assert summ['status'] == 'completed' and summ['steps'] == 250
    assert summ['deadline_misses'] == 0, summ
    assert summ['rejected_messages'] == 0
    assert 6.0 <= summ['wall_s'] <= 7.5, summ['wall_s']          # 250 steps x 25 ms
    assert summ['latency_p99_s'] < 0.025
    pr.wait_for(lambda: len(pr.by_step(c.FIELD, dt)) == 251, 10, 'all field messages')
    T = field_matrix(pr, c.FIELD, dt, N)
    ref = simulate(case.plant, case.design, 'rom_lqg', 4, range(2, 3))
    assert np.max(np.abs(T - ref.F[0])) <= 1e-9
    obj = case.design.objective
    assert bool(metrics.in_band(T, obj)) == bool(metrics.in_band(ref.F[0], obj))
    lqg_summ = json.loads((tmp_path / 'lqg.json').read_text())
    assert lqg_summ['estimator']['updates'] == 251
    # nobody subscribes to state_estimate: the lqg (estimate handed over in-process) builds none
    assert lqg_summ['estimator']['state_estimates_published'] == 0
