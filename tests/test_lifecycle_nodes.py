"""Managed (lifecycle) nodes: with autostart:=false the plant, estimator and LQR wait unconfigured
and a client drives them through the standard lifecycle services (<node>/change_state,
<node>/get_state): configure -> activate (the loop tracks) -> deactivate (no more commands;
the plant applies its safe input to the step in progress and holds) -> cleanup -> shutdown
(the processes exit 0). A configure with a bad design file fails and says why.
autostart:=true (the default) is what every other node test runs.
"""
from __future__ import annotations

import json
import re
import time

import numpy as np
import pytest

from node_harness import launcher, probe, small_case  # noqa: F401

pytestmark = pytest.mark.ros

STATE_NODES = ('/sep/plant', '/sep/estimator', '/sep/lqr')


class Lifecycle:
    """Lifecycle service clients of a probe node (its spin thread answers the futures)."""

    def __init__(self, probe):
        self.probe = probe
        self.clients = {}

    def _client(self, node: str, srv: str):
        from lifecycle_msgs.srv import ChangeState, GetState

        key = (node, srv)
        if key not in self.clients:
            typ = ChangeState if srv == 'change_state' else GetState
            client = self.probe.node.create_client(typ, f'{node}/{srv}')
            assert client.wait_for_service(timeout_sec=30.0), f'no service {node}/{srv}'
            # the client sees the server's request reader; the server's response writer may not
            # have matched the client's reader yet (discovery is asymmetric): a response sent
            # before that is lost. Settle as Probe.wait_matched does.
            time.sleep(0.5)
            self.clients[key] = client
        return self.clients[key]

    def _call(self, client, request, timeout: float = 20.0):
        fut = client.call_async(request)
        t_end = time.monotonic() + timeout
        while not fut.done():
            assert time.monotonic() < t_end, f'{client.srv_name}: no answer in {timeout} s'
            time.sleep(0.01)
        return fut.result()

    def state(self, node: str) -> str:
        from lifecycle_msgs.srv import GetState

        return self._call(self._client(node, 'get_state'), GetState.Request()).current_state.label

    def change(self, node: str, transition: str) -> bool:
        return self._call(self._client(node, 'change_state'), self._request(transition)).success

    @staticmethod
    def _request(transition: str):
        from lifecycle_msgs.msg import Transition
        from lifecycle_msgs.srv import ChangeState

        return ChangeState.Request(transition=Transition(label=transition))


def test_managed_plant_and_lqg_through_every_transition(launcher, probe, small_case, tmp_path):  # noqa: F811
    from sep_plant.ros import contract as c

    case, dt, N = small_case, small_case.dt, small_case.n_steps
    pr = probe().subscribe(c.MEASUREMENTS, c.APPLIED_INPUT, c.COMMAND)
    lqg = launcher.start('lqg', params={'design_file': case.design_file, 'autostart': False,
                                        'summary_file': tmp_path / 'lqg.json'})
    plant = launcher.start('plant', params={'scenario_file': case.scenario_file, 'autostart': False,
                                            'mode': 'realtime', 'real_time_factor': 1.0,
                                            'summary_file': tmp_path / 'plant.json'})
    lc = Lifecycle(pr)
    for node in STATE_NODES:
        assert lc.state(node) == 'unconfigured'
    time.sleep(1.0)
    assert pr.count(c.MEASUREMENTS) == 0                       # unconfigured: the plant does not step

    for node in STATE_NODES:                                    # the estimator before the LQR (lqg)
        assert lc.change(node, 'configure'), launcher.dump()
        assert lc.state(node) == 'inactive'
    time.sleep(0.5)
    assert pr.count(c.MEASUREMENTS) == 0                        # inactive: still no step
    for node in ('/sep/estimator', '/sep/lqr', '/sep/plant'):
        assert lc.change(node, 'activate')
        assert lc.state(node) == 'active'

    # active: the loop tracks (commands of the LQG come and are applied; real time at 1x, so that
    # the test's transitions land mid-episode)
    pr.wait_for(lambda: len(pr.by_step(c.APPLIED_INPUT, dt)) >= 5, 60, '5 applied inputs')
    assert len(pr.by_step(c.COMMAND, dt)) >= 4
    # deactivate the controllers: no more commands (the plant holds its input: deadline misses)
    assert lc.change('/sep/lqr', 'deactivate') and lc.change('/sep/estimator', 'deactivate')
    time.sleep(0.5)
    n_cmd, n_applied = len(pr.by_step(c.COMMAND, dt)), len(pr.by_step(c.APPLIED_INPUT, dt))
    time.sleep(1.0)
    assert len(pr.by_step(c.COMMAND, dt)) == n_cmd
    assert len(pr.by_step(c.APPLIED_INPUT, dt)) > n_applied < N
    # deactivate the plant: the step in progress (k) gets the safe input (the last applied one),
    # then the plant holds before step k + 1
    assert lc.change('/sep/plant', 'deactivate')
    time.sleep(1.0)
    k = len(pr.by_step(c.MEASUREMENTS, dt)) - 1
    assert k < N
    pr.wait_for(lambda: k in pr.by_step(c.APPLIED_INPUT, dt), 10, f'the applied input of step {k}')
    applied = pr.by_step(c.APPLIED_INPUT, dt)
    np.testing.assert_array_equal(applied[k].effort, applied[k - 1].effort)
    time.sleep(1.0)
    assert len(pr.by_step(c.MEASUREMENTS, dt)) == k + 1         # holding before step k + 1
    assert plant.returncode is None and lqg.returncode is None
    for node in STATE_NODES:
        assert lc.state(node) == 'inactive'

    for node in ('/sep/plant', '/sep/lqr', '/sep/estimator'):
        assert lc.change(node, 'cleanup')
        assert lc.state(node) == 'unconfigured'
    plant_summary = json.loads((tmp_path / 'plant.json').read_text())   # written at cleanup
    assert plant_summary['status'] == 'cleaned_up' and plant_summary['steps'] == k + 1   # 0..k applied
    assert plant_summary['safe_input_steps'] == [k]
    assert not lc.change('/sep/plant', 'configure')             # one episode per plant process
    assert 'one episode per plant process' in plant.output()
    for node in STATE_NODES:
        assert lc.change(node, 'shutdown')
    assert plant.wait(30) == 0, plant.output()
    assert lqg.wait(30) == 0, lqg.output()
    lqg_summary = json.loads((tmp_path / 'lqg.json').read_text())
    assert lqg_summary['status'] == 'shutdown'
    assert lqg_summary['lqr']['status'] == 'cleaned_up' and lqg_summary['lqr']['commands'] == n_cmd
    assert lqg_summary['estimator']['status'] == 'cleaned_up'


def test_a_configure_with_a_bad_design_file_fails_and_says_why(launcher, probe, tmp_path):  # noqa: F811
    bad = tmp_path / 'bad_design.npz'
    bad.write_bytes(b'not a design file')
    lqr = launcher.start('lqr', params={'design_file': bad, 'autostart': False})
    lc = Lifecycle(probe())
    assert lc.state('/sep/lqr') == 'unconfigured'
    assert not lc.change('/sep/lqr', 'configure')
    assert lc.state('/sep/lqr') == 'unconfigured'
    assert lqr.returncode is None                             # a managed node stays up
    out = lqr.output()
    assert 'configure failed, staying unconfigured: design_file:' in out and str(bad) in out, out
    assert lc.change('/sep/lqr', 'shutdown')
    assert lqr.wait(30) == 0, lqr.output()


def test_managed_recorder_records_only_while_active(launcher, probe, tmp_path):  # noqa: F811
    from sep_control.bags.storage import read_raw
    from sep_plant.ros import contract as c

    bag = tmp_path / 'bag'
    rec = launcher.start('record', '--out', str(bag), '--topics', 'measurements', '--no-stop-at-end',
                         params={'autostart': False})
    pr = probe()
    lc = Lifecycle(pr)
    node = '/sep_recorder'
    assert lc.state(node) == 'unconfigured'
    assert not bag.exists()                                   # configure creates the bag
    assert lc.change(node, 'configure') and lc.state(node) == 'inactive'
    assert bag.exists()
    pub = pr.publisher(c.MEASUREMENTS)
    pr.wait_for(lambda: pub.get_subscription_count() > 0, 20, 'the recorder subscribed')
    time.sleep(0.5)

    def send(steps):
        for k in steps:
            pub.publish(c.joint_state(k, 0.25, ['y0'], position=np.array([float(k)])))
        time.sleep(2.0)

    send(range(0, 3))                                         # inactive: not recorded
    assert lc.change(node, 'activate') and lc.state(node) == 'active'
    send(range(3, 8))                                         # active: recorded
    assert lc.change(node, 'deactivate') and lc.state(node) == 'inactive'
    send(range(8, 10))                                        # inactive again: not recorded
    assert lc.change(node, 'cleanup') and lc.state(node) == 'unconfigured'
    raw = read_raw(bag)                                       # closed by cleanup: a complete bag
    from rclpy.serialization import deserialize_message
    steps = [c.step_of_stamp(deserialize_message(d, c.TOPIC_TYPES[c.MEASUREMENTS]).header.stamp, 0.25)
             for d in raw.data]
    assert steps == [3, 4, 5, 6, 7]
    assert (bag / 'metadata.yaml').exists()
    assert lc.change(node, 'shutdown')
    assert rec.wait(30) == 0, rec.output()
    # the 2 sent after the deactivate are dropped (the first 3 too, unless discovery lost some)
    dropped = re.search(r'cleaned up: bag closed \((\d+) messages dropped while inactive\)', rec.output())
    assert dropped and 2 <= int(dropped.group(1)) <= 5, rec.output()


def test_a_deactivated_plant_holds_and_resumes_on_activate(launcher, probe, small_case, tmp_path):  # noqa: F811
    """The controllers autostart (their lifecycle state: active, as before); the managed plant
    holds while inactive and finishes the episode once activated again (real time at 2x: a
    lockstep episode of the small case is over in 0.1 s, before a test's transition lands)."""
    from sep_plant.ros import contract as c

    case, dt, N = small_case, small_case.dt, small_case.n_steps
    pr = probe().subscribe(c.MEASUREMENTS, c.APPLIED_INPUT)
    launcher.start('lqg', params={'design_file': case.design_file, 'estimate_timeout_s': 0.0})
    plant = launcher.start('plant', params={'scenario_file': case.scenario_file, 'autostart': False,
                                            'mode': 'realtime', 'real_time_factor': 2.0,
                                            'summary_file': tmp_path / 'plant.json'})
    lc = Lifecycle(pr)
    assert lc.state('/sep/lqr') == 'active' and lc.state('/sep/estimator') == 'active'   # autostart
    assert lc.change('/sep/plant', 'configure') and lc.change('/sep/plant', 'activate')
    pr.wait_for(lambda: len(pr.by_step(c.APPLIED_INPUT, dt)) >= 5, 60, '5 applied inputs')
    assert lc.change('/sep/plant', 'deactivate')
    time.sleep(0.5)
    held = len(pr.by_step(c.MEASUREMENTS, dt))
    time.sleep(1.5)
    assert len(pr.by_step(c.MEASUREMENTS, dt)) == held < N + 1          # no step while inactive
    assert plant.returncode is None
    assert lc.change('/sep/plant', 'activate')
    assert plant.wait(120) == 0, plant.output()
    summary = json.loads((tmp_path / 'plant.json').read_text())
    assert summary['status'] == 'completed' and summary['steps'] == N
    pr.wait_for(lambda: len(pr.by_step(c.MEASUREMENTS, dt)) == N + 1, 10, 'every measurement')
    pr.wait_for(lambda: len(pr.by_step(c.APPLIED_INPUT, dt)) == N, 10, 'every applied input')
