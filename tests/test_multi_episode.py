"""Episode after episode in one graph (issue 30): a plant with ``episodes`` K plays runs run..run+K-1
one after the other, announcing each with a scenario message carrying an "episode" entry; the lqg
resets its filter and controller per episode without a restart, and every episode equals the
offline closed loop of its seed and run to 1e-9. A design swap through ``next_design_file`` is
checked at once (a refused one says why and leaves the design in use) and used from the next
episode. One bag holds all episodes; `sep analyze` reports each and the pooled metrics.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from node_harness import SMALL, _cached_case, launcher, probe, small_case  # noqa: F401
from sep_control.evaluation.montecarlo import simulate

SEED, RUN = 7, 2


def start_graph(launcher, case, tmp_path, episodes: int, *, record: bool = False, design_file=None, **plant):
    """lqg (+ recorder) first, then the plant with `episodes` (its trajectories per episode)."""
    ctl = {'design_file': design_file or case.design_file, 'wait_for_scenario_s': 30.0,
           'episode_log_file': tmp_path / 'lqg_episodes.jsonl', 'summary_file': tmp_path / 'lqg.json'}
    lqg = launcher.start('lqg', params=ctl)
    rec = None
    subscribers = 1
    if record:
        rec = launcher.start('record', '--out', str(tmp_path / 'bag'), '--ready-file', str(tmp_path / 'ready'),
                             '--topics', 'scenario', 'measurements', 'applied_input', 'command', 'field',
                             'field_estimate', 'state_estimate', '--ready-topics', 'command', 'state_estimate')
        subscribers = 2
        plant.setdefault('wait_for_field_subscribers', 1)
        # the lqg's two nodes and the recorder hold episode 0's announcement before y_0 (a recorder
        # whose scenario reader matched after it would split the bag without episode 0)
        plant.setdefault('wait_for_scenario_subscribers', 3)
        t_end = time.monotonic() + 60
        while not (tmp_path / 'ready').exists():
            assert time.monotonic() < t_end, rec.output()
            time.sleep(0.1)
    params = {'scenario_file': case.scenario_file, 'seed': SEED, 'run': RUN, 'episodes': episodes,
              'wait_for_subscribers': subscribers, 'summary_file': tmp_path / 'plant.json',
              'episode_log_file': tmp_path / 'plant_episodes.jsonl', 'trajectory_file': tmp_path / 'traj.npz',
              'command_timeout_s': 20.0, **plant}
    return lqg, rec, launcher.start('plant', params=params)


def read_lines(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def assert_offline(case, tmp_path, episodes: int, design=None):
    """Each episode's trajectory equals the offline closed loop of run RUN + i to 1e-9."""
    ref = simulate(case.plant, design or case.design, 'rom_lqg', SEED, range(RUN, RUN + episodes))
    for i in range(episodes):
        tr = np.load(tmp_path / f'traj.e{i}.npz')
        assert int(tr['run']) == RUN + i
        assert np.max(np.abs(tr['U'] - ref.U[i])) <= 1e-9, i
        assert np.max(np.abs(tr['F'] - ref.F[i])) <= 1e-9, i


@pytest.mark.ros
def test_three_episodes_equal_offline_one_bag_analyzed(launcher, small_case, tmp_path):
    from sep_control.bags.episodes import analyze_episodes, read_episodes
    from sep_control.bags.report import metrics_rows

    lqg, rec, plant = start_graph(launcher, small_case, tmp_path, 3, record=True)
    assert plant.wait(120) == 0, plant.output()
    assert lqg.wait(30) == 0, lqg.output()           # the last episode announced: the lqg exits after it
    assert rec.wait(30) == 0, rec.output()           # the recorder stops after the last episode's step N
    summ = json.loads((tmp_path / 'plant.json').read_text())
    assert summ['episodes'] == {'played': 3, 'by_status': {'completed': 3}, 'deadline_misses': 0,
                                'rejected_messages': 0}
    recs = read_lines(tmp_path / 'plant_episodes.jsonl')
    assert [(r['episode'], r['run'], r['status'], r['steps']) for r in recs] == [
        (i, RUN + i, 'completed', small_case.n_steps) for i in range(3)]
    assert 'restart' not in lqg.output().lower() or 'restarts' in lqg.output()
    assert_offline(small_case, tmp_path, 3)
    ctl = read_lines(tmp_path / 'lqg_episodes.jsonl')      # one record per node and episode
    assert [(r['node'], r['episode'], r['status']) for r in ctl] == [
        (node, i, 'completed') for i in range(3) for node in ('estimator', 'lqr')]
    assert all(r['commands'] == small_case.n_steps for r in ctl if r['node'] == 'lqr')
    assert json.loads((tmp_path / 'lqg.json').read_text())['estimator']['episodes_played'] == 3
    # one bag, split per episode: each episode's applied inputs are the trajectory's
    eps = read_episodes(tmp_path / 'bag')
    assert [(e.index, e.run) for e in eps] == [(0, RUN), (1, RUN + 1), (2, RUN + 2)]
    for e in eps:
        tr = np.load(tmp_path / f'traj.e{e.index}.npz')
        np.testing.assert_array_equal(e.episode.u, tr['U'])
        np.testing.assert_array_equal(e.episode.F, tr['F'])
    rep = analyze_episodes(tmp_path / 'bag', small_case.design_file)
    rows = metrics_rows(rep)
    assert list(rows) == ['bag.e0', 'bag.e1', 'bag.e2', 'all episodes']
    for i in range(3):     # each row is that episode's: the offline Monte Carlo of its one run
        ref = simulate(small_case.plant, small_case.design, 'rom_lqg', SEED, range(RUN + i, RUN + i + 1)).summary
        assert rows[f'bag.e{i}']['cost_mean'] == pytest.approx(ref['cost_mean'], rel=1e-5)
        assert rows[f'bag.e{i}']['in_band'] == ref['in_band']
    assert rows['all episodes']['n_runs'] == 3
    # `sep analyze BAG` prints the same rows
    out = subprocess.run([sys.executable, '-m', 'sep_control.cli.main', 'analyze', str(tmp_path / 'bag'), '--design',
                          str(small_case.design_file), '--no-figures', '--quiet', '--out', str(tmp_path / 'rep')],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert all(name in out.stdout for name in rows), out.stdout


@pytest.mark.ros
def test_default_is_one_episode_without_episode_entry(launcher, small_case, tmp_path):
    lqg, _, plant = start_graph(launcher, small_case, tmp_path, 1)
    assert plant.wait(120) == 0 and lqg.wait(30) == 0
    summ = json.loads((tmp_path / 'plant.json').read_text())
    assert 'episodes' not in summ and summ['status'] == 'completed'
    assert not (tmp_path / 'plant_episodes.jsonl').exists()
    tr = np.load(tmp_path / 'traj.npz')                    # one file, as before
    ref = simulate(small_case.plant, small_case.design, 'rom_lqg', SEED, range(RUN, RUN + 1))
    assert np.max(np.abs(tr['U'] - ref.U[0])) <= 1e-9


@pytest.fixture(scope='session')
def other_design(tmp_path_factory):
    """The small scenario designed with another LQR weight: a second design for swaps."""
    return _cached_case(tmp_path_factory, 'small_r2', settings={'n_r': 6}, **SMALL)


def set_param(probe_node, node: str, name: str, value: str):
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    cli = probe_node.node.create_client(SetParameters, f'{node}/set_parameters')
    assert cli.wait_for_service(timeout_sec=30.0)
    time.sleep(0.5)
    req = SetParameters.Request(parameters=[Parameter(name=name, value=ParameterValue(
        type=ParameterType.PARAMETER_STRING, string_value=str(value)))])
    fut = cli.call_async(req)
    t_end = time.monotonic() + 20
    while not fut.done():
        assert time.monotonic() < t_end
        time.sleep(0.01)
    return fut.result().results[0]


@pytest.mark.ros
def test_design_swap_refused_then_accepted(launcher, probe, small_case, other_design, tmp_path, tmp_path_factory):
    """A swap set on the running lqg: a design for another plant is refused at once (the result and
    the log say why; set on the LQR, which uses the estimator's design, refused too); an accepted one
    is used from the next episode: episode 0 runs the start design, episode 1 the new one, each equal
    to its offline closed loop."""
    bad = _cached_case(tmp_path_factory, 'small_n30', n_x=30, n_steps=40, k_band=24, lqr_k_switch=20)
    pr = probe()
    ctl = {'design_file': small_case.design_file, 'scenario_file': small_case.scenario_file,
           'wait_for_scenario_s': 30.0, 'episode_log_file': tmp_path / 'lqg_episodes.jsonl',
           'summary_file': tmp_path / 'lqg.json'}
    lqg = launcher.start('lqg', params=ctl)
    refused = set_param(pr, '/sep/estimator', 'next_design_file', bad.design_file)
    assert not refused.successful and 'refused' in refused.reason and 'n_x' in refused.reason, refused.reason
    assert not set_param(pr, '/sep/lqr', 'next_design_file', other_design.design_file).successful
    ok = set_param(pr, '/sep/estimator', 'next_design_file', other_design.design_file)
    assert ok.successful, ok.reason
    plant = launcher.start('plant', params={
        'scenario_file': small_case.scenario_file, 'seed': SEED, 'run': RUN, 'episodes': 2,
        'summary_file': tmp_path / 'plant.json', 'trajectory_file': tmp_path / 'traj.npz', 'command_timeout_s': 20.0})
    assert plant.wait(120) == 0, plant.output()
    assert lqg.wait(30) == 0, lqg.output()
    assert 'next_design_file' in lqg.output() and 'refused' in lqg.output()
    ctl = read_lines(tmp_path / 'lqg_episodes.jsonl')
    assert [(r['node'], r['episode'], r['design_file']) for r in ctl] == [
        ('estimator', 0, str(small_case.design_file)), ('lqr', 0, str(small_case.design_file)),
        ('estimator', 1, str(other_design.design_file)), ('lqr', 1, str(other_design.design_file))]
    summ = json.loads((tmp_path / 'lqg.json').read_text())
    assert summ['estimator']['design_file'] == str(other_design.design_file)
    assert summ['lqr']['design_file'] == str(other_design.design_file)
    for i, case in enumerate((small_case, other_design)):
        ref = simulate(small_case.plant, case.design, 'rom_lqg', SEED, range(RUN + i, RUN + i + 1))
        tr = np.load(tmp_path / f'traj.e{i}.npz')
        assert np.max(np.abs(tr['U'] - ref.U[0])) <= 1e-9, i


# ---------------------------------------------------------------------------- pure parts
@pytest.mark.parametrize('busy', [False, True])
def test_episode_switch(busy):
    """The first announcement is the episode joined; a later one resets at once between episodes,
    else once step N is handled or a stale stamp shows the old episode was cut off."""
    from sep_estimator.episode_switch import EpisodeSwitch

    sw = EpisodeSwitch()
    assert not sw.multi and sw.last_episode()                  # a single-episode plant: done after N
    assert sw.announce(0, 3, busy=True) is False and sw.index == 0 and sw.multi and not sw.last_episode()
    assert sw.announce(0, 3, busy=False) is False               # the latched copy again
    assert sw.announce(1, 3, busy=busy) is (not busy)
    assert sw.index == (0 if busy else 1) and sw.pending == (1 if busy else None)
    assert sw.take_pending() is busy and sw.index == 1 and sw.take_pending() is False
    sw.announce(2, 3, busy=False)
    assert sw.last_episode()
    forever = EpisodeSwitch()
    forever.announce(5, 0, busy=False)
    assert not forever.last_episode()                            # episodes 0: until stopped


def test_episode_entry_round_trip_and_refusals():
    from sep_plant.scenario import (ScenarioError, episode_entry, load_scenario, scenario_message_parts,
                                    scenario_payload)

    scen = load_scenario(None)
    plain = scenario_payload(scen, scen.info)
    assert '"episode"' not in plain and scenario_message_parts(plain)[3] is None
    text = scenario_payload(scen, scen.info, episode=episode_entry(2, 5, 7, 9))
    assert scenario_message_parts(text)[3] == {'index': 2, 'of': 5, 'seed': 7, 'run': 9}
    for bad in ({'index': 5, 'of': 5, 'seed': 0, 'run': 0}, {'index': -1, 'of': 0, 'seed': 0, 'run': 0},
                {'index': 'x', 'of': 0, 'seed': 0, 'run': 0}):
        with pytest.raises(ScenarioError, match='episode'):
            scenario_message_parts(text.replace('"episode": {"index": 2, "of": 5, "run": 9, "seed": 7}',
                                                '"episode": ' + json.dumps(bad)))


@pytest.mark.ros
def test_cut_off_episodes_go_on(launcher, small_case, tmp_path):
    """Lockstep without a controller: each episode is cut off after command_timeout_s (status
    timeout, logged) and the next one starts; the plant then exits 0 (a single episode exits 3)."""
    plant = launcher.start('plant', params={
        'scenario_file': small_case.scenario_file, 'episodes': 2, 'wait_for_subscribers': 0,
        'command_timeout_s': 0.3, 'episode_log_file': tmp_path / 'eps.jsonl', 'summary_file': tmp_path / 'plant.json'})
    assert plant.wait(60) == 0, plant.output()
    assert [(r['episode'], r['status'], r['steps']) for r in read_lines(tmp_path / 'eps.jsonl')] == [
        (0, 'timeout', 0), (1, 'timeout', 0)]
    assert json.loads((tmp_path / 'plant.json').read_text())['episodes']['by_status'] == {'timeout': 2}
    assert 'cut off at step 0' in plant.output()


def test_split_a_bag_of_three_synthetic_episodes(tmp_path):
    """A bag of three episodes (each announced by its scenario message, receive times one after
    the other): read_episodes gives each with its index and run, analyze_episodes a row each and the
    pooled row; a bag without episode entries is one episode (index None), as before."""
    import dataclasses

    from bag_synth import episode_messages, synthetic_episode, write_bag, write_messages
    from sep_control.bags.episodes import analyze_episodes, read_episodes
    from sep_control.bags.report import metrics_rows
    from sep_plant.scenario import episode_entry, scenario_payload

    msgs = []
    eps = [synthetic_episode(seed=i) for i in range(3)]
    for i, ep in enumerate(eps):
        ep = dataclasses.replace(ep, payload=scenario_payload(ep.scenario, ep.info, episode=episode_entry(i, 3, 4, 10 + i)))
        shift = i * 10**12                         # episode i received after episode i-1
        msgs += [(t, ns + shift, d) for t, ns, d in episode_messages(ep)]
    bag = write_messages(tmp_path / 'three', msgs)
    got = read_episodes(bag)
    assert [(e.index, e.seed, e.run) for e in got] == [(0, 4, 10), (1, 4, 11), (2, 4, 12)]
    for e, ep in zip(got, eps):
        np.testing.assert_array_equal(e.episode.u, ep.u)
        np.testing.assert_array_equal(e.episode.y, ep.y)
        assert not e.episode.notes or all('off the step grid' not in n for n in e.episode.notes)
    rows = metrics_rows(analyze_episodes(bag))
    assert list(rows) == ['three.e0', 'three.e1', 'three.e2', 'all episodes'] and rows['all episodes']['n_runs'] == 3
    one = read_episodes(write_bag(tmp_path / 'one', eps[0]))
    assert len(one) == 1 and one[0].index is None
