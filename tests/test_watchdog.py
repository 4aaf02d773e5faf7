"""The nodes' middleware watchdog (sep_plant.node_util._Watchdog): a phase that blocks past its
bound ends the process with every thread's stack on stderr and the chosen exit code."""
import subprocess
import sys
import textwrap

from conftest import REPO_ROOT, clean_env

SCRIPT = textwrap.dedent("""
    import time
    from sep_plant.node_util import _Watchdog
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
