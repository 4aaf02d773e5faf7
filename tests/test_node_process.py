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
