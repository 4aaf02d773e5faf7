"""The nodes' middleware watchdog (sep_plant.ros.process._Watchdog): a phase that blocks past its
bound ends the process with every thread's stack on stderr and the chosen exit code."""
import subprocess
import sys
import textwrap

from conftest import REPO_ROOT, clean_env
from node_harness import launcher, small_case  # noqa: F401

SCRIPT = textwrap.dedent("""
    import time
    from sep_plant.ros.process import _Watchdog
    quick = _Watchdog(5.0, 'never fires', lambda: 9)
    quick.disarm()
    _Watchdog(0.3, 'demo: the middleware did not shut down within 0.3 s', lambda: 7)
    def stuck_in_teardown():
        time.sleep(30)
    stuck_in_teardown()
""")


def test_watchdog_dumps_the_stacks_and_exits_with_the_code():
    env = clean_env(PYTHONPATH=f"{REPO_ROOT}/sep_plant")
    p = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=25)
    assert p.returncode == 7, p.stderr
    assert "watchdog: demo: the middleware did not shut down within 0.3 s" in p.stderr
    assert "stuck_in_teardown" in p.stderr          # the blocked thread's stack is in the log
    assert "never fires" not in p.stderr


def test_sigusr1_dumps_a_running_nodes_stacks_and_it_goes_on(launcher, small_case):
    """`kill -USR1` on a node (the demo does it to a child that has not finished in time) writes
    every thread's Python stack to its log; the node keeps running."""
    import signal
    import time

    p = launcher.start('plant', params={'scenario_file': small_case.scenario_file, 'wait_for_subscribers': 1,
                                        'start_timeout_s': 60.0})
    deadline = time.monotonic() + 30
    while 'waiting for' not in p.output() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert 'waiting for' in p.output(), p.output()
    p.signal(signal.SIGUSR1)
    deadline = time.monotonic() + 10
    while 'most recent call first' not in p.output() and time.monotonic() < deadline:
        time.sleep(0.1)
    out = p.output()
    assert 'most recent call first' in out and '_wait_for_peers' in out, out
    time.sleep(0.5)
    assert p.returncode is None, out          # still waiting for its controller
