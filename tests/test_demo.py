"""The main job's executable on a small scenario: design, plant + lqg (+ record) over topics,
metrics printed and written as JSON with the DESIGN.md §3 keys."""
import json

import pytest

from node_harness import launcher, small_case  # noqa: F401
from sep_control.metrics import JSON_KEYS

pytestmark = pytest.mark.ros


@pytest.mark.parametrize('extra', [[], ['--no-record', '--three', '--mode', 'realtime', '--rtf', '10']],
                         ids=['lqg+record', 'three-processes-realtime'])
def test_demo_small(launcher, small_case, tmp_path, extra):
    out = tmp_path / 'demo'
    p = launcher.start('demo', '--out', str(out), '--scenario', str(small_case.scenario_file),
                       '--seed', '3', '--json', str(tmp_path / 'm.json'), *extra)
    assert p.wait(180) == 0, p.output()
    text = p.output()
    m = json.loads((tmp_path / 'm.json').read_text())
    for k in ('cost_mean', 'in_band', 'rms', 'mean_dev_start', 'mean_dev_end', 'n_runs',
              'deadline_misses', 'rejected_messages', 'latency_p50_s', 'latency_p99_s'):
        assert k in m and k in JSON_KEYS
    assert m['n_runs'] == 1 and m['in_band'] == 1.0
    if not extra:   # lockstep: nothing can be late
        assert m['deadline_misses'] == 0 and m['rejected_messages'] == 0, m['rejected_by_node']
    assert 'rom_lqg (topics)' in text and (out / 'design.npz').is_file()
    if not extra:
        assert (out / 'bag' / 'metadata.yaml').is_file(), text
        assert 'report:' in text and 'coverage_2sigma' in m
    # a second run reuses the design file
    if extra:
        p2 = launcher.start('demo', '--out', str(out), '--scenario', str(small_case.scenario_file),
                            '--no-record', name='demo_again')
        assert p2.wait(180) == 0, p2.output()
        assert 'reusing design file' in p2.output()
