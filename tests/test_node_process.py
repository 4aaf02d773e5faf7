"""How a node process ends on an unexpected error, and /diagnostics when a node's health() fails
(sep_plant.ros.process.run_node, sep_plant.ros.base.NodeBase.publish_diagnostics).

Each case runs in a child interpreter (run_node installs signal handlers and rclpy.init), with
the sources of this checkout first on its path.
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from conftest import REPO_ROOT, clean_env

pytest.importorskip("rclpy", reason="the node process needs rclpy")

PATH = ":".join(f"{REPO_ROOT}/{p}" for p in ("sep_plant", "sep_estimator", "sep_control"))

MID_EPISODE = textwrap.dedent("""
    import sys
    from sep_plant.ros.base import NodeBase
    from sep_plant.ros.process import NodeProcess, run_node

    class Node(NodeBase):
        role = 'plant'
        def health(self):
            from sep_plant.ros import contract as c
            return c.Health(name='probe')
        def summary(self, status):
            return {'node': self.role, 'status': status, 'steps': 3}

    def episode(executor):
        raise RuntimeError('FMU rod: do step (run 0) failed (status 3, error)')

    def make(args):
        return NodeProcess([Node('probe')], 'single', episode=episode)

    sys.exit(run_node(make, ['probe', '--ros-args', '-p', 'summary_file:=' + sys.argv[1]], 'probe'))
""")

HEALTH_FAILS = textwrap.dedent("""
    import rclpy
    from sep_plant.ros.base import NodeBase

    class Node(NodeBase):
        def health(self):
            raise KeyError('estimate_age')

    rclpy.init()
    n = Node('probe')
    got = []
    n.node.create_subscription(__import__('diagnostic_msgs.msg').msg.DiagnosticArray, '/diagnostics',
                               got.append, 10)
    n.publish_diagnostics()
    n.publish_diagnostics()
    for _ in range(50):
        rclpy.spin_once(n.node, timeout_sec=0.05)
        if len(got) >= 2:
            break
    print('STATUS', [(s.level, s.message) for a in got for s in a.status], flush=True)
    n.destroy_node()
    rclpy.shutdown()
""")


IN_A_CALLBACK = textwrap.dedent("""
    import sys
    from sep_plant.ros.base import NodeBase
    from sep_plant.ros.process import NodeProcess, run_node

    class Node(NodeBase):
        role = 'estimator'
        def __init__(self):
            super().__init__('probe')
            self.node.create_timer(0.05, self.boom)
        def boom(self):
            raise FloatingPointError('filter: covariance not positive definite at step 4')
        def summary(self, status):
            return {'node': self.role, 'status': status}

    sys.exit(run_node(lambda a: NodeProcess([Node()], sys.argv[2]),
                      ['probe', '--ros-args', '-p', 'summary_file:=' + sys.argv[1]], 'probe'))
""")


def child(script: str, *args: str) -> subprocess.CompletedProcess:
    env = clean_env(PYTHONPATH=PATH, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    return subprocess.run([sys.executable, "-c", script, *args], env=env, capture_output=True, text=True,
                          timeout=60, stdin=subprocess.DEVNULL)


def test_an_unexpected_error_mid_episode_writes_an_error_summary(tmp_path):
    """0.8.0 skipped finish() on any exception other than a start or episode error: no summary."""
    summary = tmp_path / "summary.json"
    p = child(MID_EPISODE, str(summary))
    assert p.returncode == 1, p.stderr
    assert summary.exists(), p.stderr
    summ = json.loads(summary.read_text())
    assert summ["status"] == "error" and summ["steps"] == 3
    assert summ["error"] == "RuntimeError: FMU rod: do step (run 0) failed (status 3, error)"
    assert "unexpected error, stopping: RuntimeError" in p.stderr and "Traceback" in p.stderr


def test_a_failing_health_is_logged_and_published_as_an_error(tmp_path):
    """0.8.0 swallowed any exception of health() with `except Exception: pass`: /diagnostics went
    silent and nothing said why."""
    p = child(HEALTH_FAILS)
    assert p.returncode == 0, p.stderr
    assert "health() failed: KeyError: 'estimate_age'" in p.stderr
    assert p.stderr.count("Traceback") == 1                 # the traceback once, not per period
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("STATUS"))
    assert "health() failed: KeyError" in line and "b'\\x02'" in line, line


STOPS_MID_EPISODE = textwrap.dedent("""
    import sys
    from sep_plant.ros.base import NodeBase, StopError
    from sep_plant.ros.process import NodeProcess, run_node

    class Node(NodeBase):
        role = 'lqg'
        def summary(self, status):
            return {'node': self.role, 'status': status}

    def episode(executor):
        raise StopError('the plant scenario changed mid-episode (after step 7) and no longer fits the design')

    sys.exit(run_node(lambda a: NodeProcess([Node('probe')], 'single', episode=episode),
                      ['probe', '--ros-args', '-p', 'summary_file:=' + sys.argv[1]], 'probe'))
""")


def _designed(last_k: int):
    """A stand-in for a DesignedNode (only what `_on_scenario` reads) after `last_k` steps."""
    from types import SimpleNamespace

    from sep_estimator.ros.designed_node import DesignedNode

    node = SimpleNamespace(design=None, allow_model_mismatch=False, design_file="d.npz", last_k=last_k,
                           fatal=None, sub_scenario=SimpleNamespace(topic_name="/sep/scenario"))
    node._scenario_refused = lambda why: DesignedNode._scenario_refused(node, why)
    return node, DesignedNode._on_scenario


def test_a_scenario_that_changes_mid_episode_says_the_node_stops_and_why(monkeypatch):
    """0.8.0 logged 'refusing to start' for a scenario that changed after the node had run steps."""
    from sep_estimator import design_file, model_mismatch
    from sep_plant import scenario

    def mismatch(*args, **kwargs):
        raise design_file.DesignFileError("design file d.npz: plant n_u 3 != 2")

    monkeypatch.setattr(scenario, "parse_scenario_message", lambda data: (None, None, None))
    monkeypatch.setattr(model_mismatch, "model_mismatch", mismatch)
    before, on_scenario = _designed(-1)
    on_scenario(before, type("Msg", (), {"data": "{}"})())
    assert before.fatal.lead == "refusing to start"                 # at start: a refusal, as before
    after, _ = _designed(7)
    on_scenario(after, type("Msg", (), {"data": "{}"})())
    msg = str(after.fatal)
    assert after.fatal.lead == "stopping" and after.fatal.exit_code == 2
    assert "changed mid-episode (after step 7)" in msg and "stops commanding" in msg and "n_u 3 != 2" in msg


def test_a_node_that_stops_mid_episode_logs_stopping_and_writes_its_summary(tmp_path):
    summary = tmp_path / "summary.json"
    p = child(STOPS_MID_EPISODE, str(summary))
    assert p.returncode == 2, p.stderr
    assert "stopping: the plant scenario changed mid-episode" in p.stderr and "refusing to start" not in p.stderr
    summ = json.loads(summary.read_text())
    assert summ["status"] == "error" and "changed mid-episode" in summ["error"]


@pytest.mark.parametrize("executor", ["events", "single"])
def test_an_error_in_a_callback_writes_an_error_summary(tmp_path, executor):
    """A controller's error is raised in a subscription or timer callback (a filter error): it
    leaves the executor's spin and ends the process the same way, summary first."""
    summary = tmp_path / "summary.json"
    p = child(IN_A_CALLBACK, str(summary), executor)
    assert p.returncode == 1, p.stderr
    summ = json.loads(summary.read_text())
    assert summ == {"node": "estimator", "status": "error",
                    "error": "FloatingPointError: filter: covariance not positive definite at step 4"}
