"""`sep` on the venv's PATH after `make build`: .venv/bin/sep (written by ros_ws/link_venv.sh) runs
the colcon install in ros_ws/install, the same copy as the ROS executables, from a fresh shell
that did not source install/setup.sh.  Skipped (with the reason) where this checkout has no
build: `make test` always builds first."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

import sep_plant

REPO_ROOT = Path(__file__).resolve().parent.parent
VENV = Path(sys.prefix)
INSTALL = REPO_ROOT / 'ros_ws' / 'install'
LAUNCHER = VENV / 'bin' / 'sep'
MARK = 'written by ros_ws/link_venv.sh of sep'
PACKAGES = ('sep_plant', 'sep_estimator', 'sep_control')


@pytest.fixture(scope='module')
def launcher() -> Path:
    exe = INSTALL / 'sep_control' / 'lib' / 'sep_control' / 'sep'
    if not exe.is_file():
        pytest.skip(f'no build: {exe} is missing (run `make build`)')
    if not LAUNCHER.is_file() or MARK not in LAUNCHER.read_text():
        pytest.skip(f'{LAUNCHER} is not written by `make build` (run it)')
    if f"exe='{exe}'" not in LAUNCHER.read_text():
        pytest.skip(f'{LAUNCHER} runs another checkout\'s install (shared venv); `make build` here')
    return LAUNCHER


def fresh_shell(command: str, **kw) -> subprocess.CompletedProcess:
    """`sh -c command` in a login-free environment: only HOME, PATH with the venv's bin first (what
    `. .venv/bin/activate` does to PATH), no sourced workspace, no ROS variables."""
    env = {'HOME': os.environ.get('HOME', '/tmp'), 'PATH': f'{VENV}/bin:/usr/bin:/bin',
           'MPLBACKEND': 'Agg', 'LANG': 'C.UTF-8'}
    return subprocess.run(['sh', '-c', command], env=env, capture_output=True, text=True,
                          stdin=subprocess.DEVNULL, timeout=120, cwd='/', **kw)


def test_sep_version(launcher):
    proc = fresh_shell('command -v sep && sep --version')
    assert proc.returncode == 0, proc.stderr
    path, version = proc.stdout.splitlines()[:2]
    assert Path(path) == launcher
    assert sep_plant.__version__ in version


def test_sep_design_help(launcher):
    proc = fresh_shell('sep design --help')
    assert proc.returncode == 0, proc.stderr
    assert 'usage' in proc.stdout.lower() and '--scenario' in proc.stdout


def test_venv_python_imports_the_install(launcher):
    """The .pth in the venv's site-packages: the venv's python imports ros_ws/install's copy."""
    code = 'import sep_plant, sep_estimator, sep_control as c; print(sep_plant.__file__); ' \
           'print(sep_estimator.__file__); print(c.__file__)'
    proc = fresh_shell(f'python -c "{code}"')
    assert proc.returncode == 0, proc.stderr
    for pkg, path in zip(PACKAGES, proc.stdout.split()):
        assert Path(path).is_relative_to(INSTALL / pkg), path


def test_launcher_environment_is_that_of_setup_sh(launcher):
    """The launcher exports AMENT_PREFIX_PATH and PYTHONPATH as install/setup.sh does: the ament
    index finds the three packages there (how `sep demo` finds the node executables)."""
    lines = launcher.read_text().splitlines()
    assert lines[-1] == 'exec "$exe" "$@"'
    env_lines = '\n'.join(line for line in lines
                          if line.startswith(('AMENT_PREFIX_PATH=', 'PYTHONPATH=', 'export ')))
    probe = ('from ament_index_python import get_package_prefix; import os; '
             'print(os.environ["AMENT_PREFIX_PATH"]); print(os.environ["PYTHONPATH"]); '
             '[print(get_package_prefix(p)) for p in ("sep_plant", "sep_estimator", "sep_control")]')
    mine = fresh_shell(f'{env_lines}\npython -c \'{probe}\'')
    assert mine.returncode == 0, mine.stderr
    theirs = fresh_shell(f'. "{INSTALL}/setup.sh" && python -c \'{probe}\'')
    assert theirs.returncode == 0, theirs.stderr
    assert mine.stdout == theirs.stdout
    assert mine.stdout.splitlines()[2:] == [str(INSTALL / p) for p in PACKAGES]
