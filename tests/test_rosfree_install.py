"""The ROS-free install: `pip install ./sep_plant ./sep_estimator ./sep_control` without ROS gives
the offline tools (`sep design | evaluate | validate`) and what Dask workers import.

The three packages are installed from this checkout with `pip install --no-deps --target DIR`
(their dependencies are the venv's third-party packages), then used in subprocesses where ROS
cannot be imported: a sitecustomize on PYTHONPATH puts a sys.meta_path finder first that raises
ImportError for rclpy, the ROS message and interface packages and ament_index_python, and drops
every sys.path entry other than DIR that holds a sep package (the source tree, ros_ws/install
through the venv's .pth), so only DIR provides sep.
"""
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import sep_plant
from core_helpers import TINY_YAML

REPO_ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ('sep_plant', 'sep_estimator', 'sep_control')

SITECUSTOMIZE = r'''
import re
import sys
from pathlib import Path

TARGET = {target!r}
BLOCKED = re.compile(r'^(rclpy|rcl_interfaces|builtin_interfaces|ament_index_python|rosidl\w*'
                     r'|\w+_msgs)(\.|$)')


class NoRos:
    """Import of ROS refused: the ROS-free install must not need it."""

    def find_spec(self, name, path=None, target=None):
        if BLOCKED.match(name):
            raise ImportError(f'{{name}} is blocked (ROS-free install)', name=name)
        return None


sys.meta_path.insert(0, NoRos())
sys.path[:] = [p for p in sys.path if p == TARGET or not any(
    (Path(p or '.') / pkg / '__init__.py').is_file() for pkg in {packages!r})]
'''

# Imports every module outside the ros/ subpackages, checks each came from the --target folder
# and that nothing imported ROS; then that rclpy does fail (the blocker works).
IMPORT_ALL = r'''
import importlib, json, pkgutil, sys
from pathlib import Path

target, packages = Path(sys.argv[1]), sys.argv[2:]
names = []


def walk(package, path):
    for info in pkgutil.iter_modules(path, package + '.'):
        if info.name.rsplit('.', 1)[1] == 'ros':
            continue                       # the rclpy side, not imported
        module = importlib.import_module(info.name)
        names.append(info.name)
        if info.ispkg:
            walk(info.name, module.__path__)


for pkg in packages:
    names.append(pkg)
    walk(pkg, importlib.import_module(pkg).__path__)
outside = [n for n in names if not Path(sys.modules[n].__file__).is_relative_to(target)]
ros = sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'ament_index_python')
             or m.split('.')[0].endswith('_msgs'))
try:
    import rclpy  # noqa: F401
    blocked = False
except ImportError as exc:
    blocked = 'blocked' in str(exc)
print(json.dumps({'modules': names, 'outside': outside, 'ros': ros, 'rclpy_blocked': blocked}))
'''

FAST = ['--p', '5', '--q', '5', '--n-r', '10', '--ensemble', '20', '--no-belief', '--quiet']


def can_build_wheels() -> bool:
    """setuptools' bdist_wheel is there (setuptools >= 70.1, or the `wheel` package)."""
    import importlib.util
    return any(importlib.util.find_spec(m) is not None
               for m in ('setuptools.command.bdist_wheel', 'wheel'))


@pytest.fixture(scope='module')
def rosfree(tmp_path_factory):
    """(target folder, environment) of the three packages pip-installed without ROS."""
    if not can_build_wheels():
        pytest.fail(f'{sys.prefix}: no bdist_wheel (setuptools < 70.1 and no `wheel`): run `make venv` '
                    '(requirements.txt pins wheel)')
    base = tmp_path_factory.mktemp('rosfree')
    src, target, block = base / 'src', base / 'target', base / 'block'
    for pkg in PACKAGES:   # copies: an in-tree build leaves build/ and *.egg-info behind
        shutil.copytree(REPO_ROOT / pkg, src / pkg,
                        ignore=shutil.ignore_patterns('__pycache__', 'build', '*.egg-info', 'test'))
    cmd = [sys.executable, '-m', 'pip', 'install', '--no-deps', '--no-build-isolation', '--no-index',
           '--disable-pip-version-check', '--quiet', '--target', str(target),
           *(str(src / pkg) for pkg in PACKAGES)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, stdin=subprocess.DEVNULL,
                          env={k: v for k, v in os.environ.items() if k != 'PYTHONPATH'})
    assert proc.returncode == 0, f'pip install --target failed:\n{proc.stdout}\n{proc.stderr}'
    block.mkdir()
    (block / 'sitecustomize.py').write_text(
        SITECUSTOMIZE.format(target=str(target), packages=PACKAGES))
    env = {k: v for k, v in os.environ.items()
           if k not in ('PYTHONPATH', 'AMENT_PREFIX_PATH', 'COLCON_PREFIX_PATH', 'CMAKE_PREFIX_PATH')}
    env.update(PYTHONPATH=f'{block}{os.pathsep}{target}', MPLBACKEND='Agg')
    return target, env


def run(args, env, cwd, timeout=300):
    return subprocess.run(args, env=env, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          stdin=subprocess.DEVNULL)


def test_console_scripts_and_data_installed(rosfree):
    target, _ = rosfree
    assert (target / 'bin' / 'sep').is_file()
    assert 'sep_control.cli.main' in (target / 'bin' / 'sep').read_text()
    for pkg in PACKAGES:
        assert list((target / 'share' / pkg / 'config').glob('*.yaml')), pkg
    assert (target / 'share/sep_plant/scenarios/reference.yaml').is_file()


def test_sep_version_without_ros(rosfree, tmp_path):
    target, env = rosfree
    proc = run([str(target / 'bin' / 'sep'), '--version'], env, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert sep_plant.__version__ in proc.stdout + proc.stderr


def test_every_module_outside_ros_imports_without_ros(rosfree, tmp_path):
    target, env = rosfree
    proc = run([sys.executable, '-c', IMPORT_ALL, str(target), *PACKAGES], env, tmp_path)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.splitlines()[-1])
    assert got['outside'] == [] and got['ros'] == [], got
    assert got['rclpy_blocked'], 'the ROS blocker did not block rclpy'
    # the Dask engine and every layer of sep_control are among them
    for name in ('sep_control.compute.engine', 'sep_control.design.pipeline', 'sep_control.cli.design',
                 'sep_control.evaluation.montecarlo', 'sep_control.bags.storage',
                 'sep_estimator.design_file', 'sep_plant.scenario'):
        assert name in got['modules'], name
    assert not any('ros' in n.split('.') for n in got['modules'])


def test_sep_design_without_ros(rosfree, tmp_path):
    target, env = rosfree
    (tmp_path / 'tiny.yaml').write_text(TINY_YAML)
    out = tmp_path / 'tiny.npz'
    proc = run([str(target / 'bin' / 'sep'), 'design', '--scenario', 'tiny.yaml', '--out', str(out),
                *FAST], env, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    code = textwrap.dedent(f'''
        from sep_estimator.design_file import load_design
        d = load_design({str(out)!r})
        import sep_estimator; print(d.n_r, d.n_steps, sep_estimator.__file__)''')
    check = run([sys.executable, '-c', code], env, tmp_path)
    assert check.returncode == 0, check.stderr
    n_r, n_steps, where = check.stdout.split()
    assert (int(n_r), int(n_steps)) == (10, 40) and Path(where).is_relative_to(target)
