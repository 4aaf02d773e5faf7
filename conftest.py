"""Session-wide test set-up for sep (loaded by pytest for every test under the repo root).

It lives at the repository root rather than in tests/ so that it also applies to the
ament_python per-package test folders (sep_plant/test, sep_estimator/test, sep_control/test);
fixtures that only tests/ needs are in tests/conftest.py.

At import time, i.e. before any test or subprocess starts:

* ROS isolation: a ROS_DOMAIN_ID unique to this pytest session (derived from the pid, in
  1..101, never 0, the default domain that other ROS 2 software on the machine uses) and
  ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, written to os.environ so that nodes started in
  this process and every subprocess (ros2-run style executables) inherit them.  Set
  SEP_TEST_ROS_DOMAIN_ID to force a particular domain.
* Headless plotting: MPLBACKEND=Agg unless already set.
* Imports without building: the three package source roots go on sys.path (so
  ``import sep_plant.slab`` works from a plain checkout), plus tests/ for shared helpers
  (pytest runs in importlib mode, see pytest.ini).
"""
import os
import sys

REPO_ROOT = os.path.dirname(os.path.abspath(__file__))
PACKAGES = ('sep_plant', 'sep_estimator', 'sep_control')


def _session_domain_id() -> int:
    forced = os.environ.get('SEP_TEST_ROS_DOMAIN_ID')
    if forced:
        return int(forced)
    return 1 + os.getpid() % 101


os.environ['ROS_DOMAIN_ID'] = str(_session_domain_id())
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_LOCALHOST_ONLY', None)  # deprecated in Jazzy; it would override the above
os.environ.pop('ROS_STATIC_PEERS', None)
os.environ.setdefault('MPLBACKEND', 'Agg')

for _path in [os.path.join(REPO_ROOT, 'tests')] + [os.path.join(REPO_ROOT, p) for p in PACKAGES]:
    if _path not in sys.path:
        sys.path.insert(0, _path)


def pytest_report_header(config):
    return (f"sep: ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']} "
            f"ROS_AUTOMATIC_DISCOVERY_RANGE={os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']}")
