"""The main job's executable on a small scenario: design, plant + lqg (+ record) over topics,
metrics printed and written as JSON with the metrics (docs/method.md)."""
import json
import os

import pytest

from node_harness import launcher, small_case  # noqa: F401
from sep_control.evaluation.metrics import JSON_KEYS

pytestmark = pytest.mark.ros


# real-time factor 4: a 25 ms step leaves the three processes room on a loaded 2-core CI machine
# (at 10, p50 latency 12 ms against a 10 ms step once dropped a step to the nominal fallback)
@pytest.mark.parametrize('extra', [[], ['--no-record', '--three', '--mode', 'realtime', '--real-time-factor', '4']],
                         ids=['lqg+record', 'three-processes-realtime'])
def test_demo_small(launcher, small_case, tmp_path, extra):
    out = tmp_path / 'demo'
    p = launcher.start('demo', '--out', str(out), '--scenario', str(small_case.scenario_file),
                       '--seed', '3', '--json', str(tmp_path / 'm.json'), '--timeout', '120', *extra)
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
                            '--no-record', '--timeout', '120', name='demo_again')
        assert p2.wait(180) == 0, p2.output()
        assert 'reusing design file' in p2.output()


SMALL_YAML = """\
plant: {type: slab, n_x: 20}
n_steps: 40
band_window: [24, 40]
lqr_k_switch: 20
target: TARGET
"""


def test_demo_redesigns_when_the_scenario_changed(launcher, tmp_path):
    """Two demos into one folder, the scenario's target changed from 150 to 151 in between: the
    second names the difference and designs again (nothing stale runs); a third with the same
    scenario reuses the new design."""
    from sep_estimator.design_file import load_design

    out, scen = tmp_path / 'demo', tmp_path / 'small.yaml'

    def demo(target, name):
        scen.write_text(SMALL_YAML.replace('TARGET', target))
        p = launcher.start('demo', '--out', str(out), '--scenario', str(scen), '--no-record', '--timeout', '120',
                           name=name)
        assert p.wait(180) == 0, p.output()
        return p.output()

    first = demo('150.0', 'demo_150')
    assert 'designing for' in first and 'rom_lqg (topics)' in first
    assert load_design(out / 'design.npz').problem.target == 150.0
    second = demo('151.0', 'demo_151')
    assert 'was made from other inputs; redesigning' in second and 'problem.target: 150.0 != 151.0' in second, second
    assert 'reusing design file' not in second and 'rom_lqg (topics)' in second
    d = load_design(out / 'design.npz')
    assert d.problem.target == 151.0 and float(d.objective.target[0]) == 151.0
    assert 'reusing design file' in demo('151.0', 'demo_151_again')


# A coarse sep_plant/scenarios/plate.yaml (same plant defaults: 3 x 3 lamps, 5 sensors, held edge
# x_max = 150 F, target 150 +- 3 F), 10 x 8 nodes, N = 40 at dt = 0.5 (20 s, window 15..20 s), with
# fast design settings in its `design:` section (the demo designs with DesignSettings.for_scenario).
# Offline (seed 1, runs 0..19) ROM-LQG keeps every run in band; design ~4 s.
PLATE_DEMO_YAML = """\
plant:
  type: plate
  nodes: [10, 8]
  boundary_temperatures: {x_max: 150.0}
  t_init: 100.0
  dt: 0.5
n_steps: 40
target: 150.0
band: 3.0
band_window: [30, 40]
w_std: 0.135
v_std: 0.1
u_init: 0.05
design: {p: 8, q: 8, n_r: 16, ensemble: 20, belief_iter: 1}
"""


def test_demo_grid_plant_scenario_file(launcher, tmp_path):
    """`demo --scenario FILE` with a 2-D grid plant: design -> plant + lqg over topics -> bag ->
    report with the grid plants' heat maps and the rendered field_image frame."""
    scen = tmp_path / 'plate.yaml'
    scen.write_text(PLATE_DEMO_YAML)
    out, js = tmp_path / 'demo', tmp_path / 'm.json'
    p = launcher.start('demo', '--out', str(out), '--scenario', str(scen), '--seed', '1',
                       '--domain-id', os.environ['ROS_DOMAIN_ID'], '--json', str(js))
    assert p.wait(240) == 0, p.output()
    text = p.output()
    assert 'plant plate' in text and 'rom_lqg (topics)' in text, text
    m = json.loads(js.read_text())
    for k in ('mean_dev_start', 'mean_dev_end', 'in_band'):
        assert k in m and m[k] is not None, (k, m)
    assert m['n_runs'] == 1 and m['in_band'] == 1.0 and m['mean_dev_end'] < 3.0, m
    assert m['deadline_misses'] == 0 and m['rejected_messages'] == 0, m['rejected_by_node']
    assert (out / 'design.npz').is_file()
    bag = out / 'bag'
    assert (bag / 'metadata.yaml').is_file(), text
    import yaml
    meta = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    counts = {t['topic_metadata']['name']: t['message_count'] for t in meta['topics_with_message_count']}
    # the recorder subscribed to the grid plant's images: every step's true and estimated frame
    assert counts.get('/sep/field_image') == 41 and counts.get('/sep/field_estimate_image') == 41, counts
    report = out / 'report' / 'report.md'
    assert report.is_file() and f'report: {report}' in text, text
    md = report.read_text()
    assert 'grid 10 x 8' in md, md
    for png in ('field.png', 'estimation.png', 'inputs.png', 'field_image.png'):
        assert f']({png})' in md, (png, md)
        assert (report.parent / png).stat().st_size > 0, png
    assert 'field_image at k = ' in md and '32FC1' in md


def test_demo_timeout_reports_where_the_nodes_are(launcher, small_case, tmp_path):
    """A run that does not finish within --timeout is stopped, exit 1, and the report has every
    node's log tail with its Python stacks (asked for with SIGUSR1), so a hang says where it is."""
    out = tmp_path / 'demo'
    p = launcher.start('demo', '--out', str(out), '--scenario', str(small_case.scenario_file), '--no-record',
                       '--mode', 'realtime', '--real-time-factor', '1', '--timeout', '8')      # a 10 s episode
    assert p.wait(120) == 1, p.output()
    text = p.output()
    assert 'has not finished after --timeout 8 s' in text, text
    assert '--- plant (running)' in text and '--- lqg (running)' in text, text
    assert 'most recent call first' in text, text
