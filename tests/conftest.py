"""Fixtures for the integration tests in tests/.

ROS isolation (ROS_DOMAIN_ID, localhost discovery) and sys.path set-up are done once for the
whole repository by the top-level conftest.py.
"""
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ('sep_plant', 'sep_estimator', 'sep_control')

# Variables that would chain an already-sourced workspace into ours; scrubbed so that a
# test's build and environment depend only on the checkout.
_WORKSPACE_VARS = ('AMENT_PREFIX_PATH', 'COLCON_PREFIX_PATH', 'CMAKE_PREFIX_PATH', 'PYTHONPATH',
                   'COLCON_CURRENT_PREFIX')


def clean_env(**extra):
    """os.environ without sourced-workspace variables (ROS isolation variables are kept)."""
    env = {k: v for k, v in os.environ.items() if k not in _WORKSPACE_VARS}
    env.update(extra)
    return env


@dataclass
class ColconInstall:
    install: Path
    env: dict = field(repr=False)  # environment after `. install/setup.sh`

    def prefix(self, package):
        return self.install / package

    def run(self, args, timeout=120, **kwargs):
        """Run ``args`` (argv list) with the install's environment, like a shell that sourced
        install/setup.sh."""
        return subprocess.run(args, env=self.env, capture_output=True, text=True,
                              stdin=subprocess.DEVNULL, timeout=timeout, **kwargs)


def sourced_env(install: Path, base_env: dict) -> dict:
    """The environment that `. <install>/setup.sh` produces, starting from base_env."""
    out = subprocess.run(['bash', '-c', '. "$1/setup.sh" >&2 && env -0', 'bash', str(install)],
                         env=base_env, capture_output=True, check=True, timeout=60,
                         stdin=subprocess.DEVNULL)
    pairs = (item.split('=', 1) for item in out.stdout.decode().split('\0') if '=' in item)
    return dict(pairs)


@pytest.fixture(scope='session')
def colcon_install(tmp_path_factory) -> ColconInstall:
    """`colcon build` of the three packages from this checkout into a fresh temporary
    workspace (build, install and log bases all under pytest's tmp dir): independent of
    whatever ros_ws/install holds."""
    base = tmp_path_factory.mktemp('colcon_ws')
    colcon = Path(sys.executable).with_name('colcon')
    if not colcon.exists():
        pytest.fail(f'colcon not found next to {sys.executable}; run `make venv`')
    cmd = [str(colcon), '--log-base', str(base / 'log'), 'build',
           '--base-paths', *(str(REPO_ROOT / p) for p in PACKAGES),
           '--build-base', str(base / 'build'), '--install-base', str(base / 'install')]
    # An inherited PYTHONDONTWRITEBYTECODE only adds setuptools warnings.
    env = clean_env(PYTHONDONTWRITEBYTECODE='')
    proc = subprocess.run(cmd, cwd=base, env=env, capture_output=True, text=True, timeout=600,
                          stdin=subprocess.DEVNULL)
    if proc.returncode != 0:
        pytest.fail(f'colcon build failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}')
    install = base / 'install'
    return ColconInstall(install=install, env=sourced_env(install, clean_env()))


@pytest.fixture
def procs():
    """A list to append started subprocesses to; every one still running is killed afterwards."""
    started: list[subprocess.Popen] = []
    yield started
    for p in started:
        if p.poll() is None:
            p.kill()
        p.wait(10)
