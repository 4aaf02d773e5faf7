"""The parameter files in ros_ws/config/ load with --params-file and reach the nodes."""
import json
import signal
from pathlib import Path

import pytest

from node_harness import launcher, small_case  # noqa: F401

pytestmark = pytest.mark.ros
CONFIG = Path(__file__).resolve().parent.parent / 'ros_ws' / 'config'


def test_plant_params_files(launcher, small_case, tmp_path):
    p = launcher.start('plant', '--ros-args', '--params-file', str(CONFIG / 'plant.yaml'),
                       '--params-file', str(CONFIG / 'plant_realtime.yaml'),
                       params={'scenario_file': small_case.scenario_file, 'wait_for_subscribers': 0,
                               'real_time_factor': 200.0, 'summary_file': tmp_path / 'p.json'})
    assert p.wait(60) == 0, p.output()
    summ = json.loads((tmp_path / 'p.json').read_text())
    assert summ['mode'] == 'realtime' and summ['real_time_factor'] == 200.0
    assert summ['deadline_misses'] == small_case.n_steps      # nobody answered: all held


@pytest.mark.parametrize('exe,files', [('lqg', ['lqg.yaml']), ('estimator', ['estimator.yaml']),
                                       ('lqr', ['lqr.yaml'])])
def test_controller_params_files(launcher, small_case, exe, files):
    args = ['--ros-args']
    for f in files:
        args += ['--params-file', str(CONFIG / f)]
    p = launcher.start(exe, *args, params={'design_file': small_case.design_file})
    out = ''
    import time
    t_end = time.monotonic() + 30
    while time.monotonic() < t_end and p.returncode is None:
        out = p.output()
        if f'design file {small_case.design_file}' in out:
            break
        time.sleep(0.1)
    assert f'design file {small_case.design_file}' in out, out
    if exe == 'lqr':
        assert 'estimate_timeout_s 0.5' in out
    p.signal(signal.SIGINT)
    assert p.wait(15) == 130, p.output()
