"""The colcon install space has the layout `ros2 run` relies on, for every executable.

ros2run resolves `ros2 run <pkg> <exe>` with ros2pkg's get_executable_paths: the package
prefix from the ament index (ament_index_python.get_package_prefix, i.e. the prefix in
AMENT_PREFIX_PATH holding share/ament_index/resource_index/packages/<pkg>), then every file
below <prefix>/lib/<pkg>/ that is executable (os.access X_OK; folders starting with '.'
skipped), keeping those whose basename is <exe>; exactly one match may remain.  We do the
same here (there is no ros2 CLI in the venv), against a fresh `colcon build` of this checkout
(the session fixture `colcon_install` in tests/conftest.py), then run each executable with
--help in a shell that sourced install/setup.sh.
"""
import os
import sys
from pathlib import Path

import pytest

PACKAGES = ('sep_plant', 'sep_estimator', 'sep_control')
EXECUTABLES = {
    'sep_plant': ('plant',),
    'sep_estimator': ('estimator',),
    'sep_control': ('sep', 'lqr', 'lqg', 'design', 'evaluate', 'validate', 'record', 'analyze',
                    'demo'),
}
CASES = [(pkg, exe) for pkg, exes in EXECUTABLES.items() for exe in exes]
REPO_ROOT = Path(__file__).resolve().parent.parent


def executable_paths(package_name):
    """ros2pkg.api.get_executable_paths, reimplemented (ros2pkg is not installed)."""
    from ament_index_python import get_package_prefix

    base_path = os.path.join(get_package_prefix(package_name), 'lib', package_name)
    paths = []
    for dirpath, dirnames, filenames in os.walk(base_path):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith('.'))
        for filename in sorted(filenames):
            path = os.path.join(dirpath, filename)
            if os.access(path, os.X_OK):
                paths.append(path)
    return paths


def resolve(package_name, executable_name):
    """ros2run's lookup: the single executable file of that name under lib/<pkg>/."""
    matches = [p for p in executable_paths(package_name)
               if os.path.basename(p) == executable_name]
    assert len(matches) == 1, f'{package_name} {executable_name}: found {matches}'
    return Path(matches[0])


@pytest.fixture
def ament_env(colcon_install, monkeypatch):
    """AMENT_PREFIX_PATH exactly as install/setup.sh sets it, for in-process index lookups."""
    monkeypatch.setenv('AMENT_PREFIX_PATH', colcon_install.env['AMENT_PREFIX_PATH'])
    return colcon_install


def test_setup_sh_exports_the_packages(colcon_install):
    env = colcon_install.env
    prefixes = env.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
    pythonpath = env.get('PYTHONPATH', '').split(os.pathsep)
    site = f'python{sys.version_info.major}.{sys.version_info.minor}'
    for pkg in PACKAGES:
        prefix = colcon_install.prefix(pkg)
        assert str(prefix) in prefixes
        assert str(prefix / 'lib' / site / 'site-packages') in pythonpath
        assert (prefix / 'share/ament_index/resource_index/packages' / pkg).is_file()
        assert (prefix / 'share' / pkg / 'package.xml').is_file()
    # The packages import from the install space (not from the source tree).
    code = ('import sep_plant, sep_estimator, sep_control; '
            'print(sep_plant.__file__, sep_estimator.__file__, sep_control.__file__)')
    proc = colcon_install.run([sys.executable, '-c', code], cwd='/')
    stderr, returncode = proc.stderr, proc.returncode
    assert returncode == 0, stderr
    for path in proc.stdout.split():
        assert Path(path).is_relative_to(colcon_install.install), path


def test_package_prefixes_from_ament_index(ament_env):
    from ament_index_python import get_package_prefix, get_packages_with_prefixes

    found = get_packages_with_prefixes()
    for pkg in PACKAGES:
        assert found[pkg] == str(ament_env.prefix(pkg))
        assert get_package_prefix(pkg) == str(ament_env.prefix(pkg))


def test_console_scripts_match_the_list(ament_env):
    """Every console script installed is one we test, and vice versa."""
    for pkg in PACKAGES:
        names = {os.path.basename(p) for p in executable_paths(pkg)}
        assert names == set(EXECUTABLES[pkg]), pkg


def test_data_files_installed(ament_env):
    """Scenario files (sep_plant) and every package's parameter files reach share/<pkg>/."""
    for pkg, sub in (('sep_plant', 'scenarios'), ('sep_plant', 'config'),
                     ('sep_estimator', 'config'), ('sep_control', 'config')):
        assert list((REPO_ROOT / pkg / sub).glob('*.yaml')), (pkg, sub)
        sources = sorted(p.name for p in (REPO_ROOT / pkg / sub).glob('*.yaml'))
        installed = sorted(p.name for p in (ament_env.prefix(pkg) / 'share' / pkg / sub).glob('*.yaml'))
        assert installed == sources, (pkg, sub)


@pytest.mark.parametrize('package_name,executable_name', CASES,
                         ids=[f'{p}-{e}' for p, e in CASES])
def test_executable_resolves_and_runs(ament_env, package_name, executable_name):
    path = resolve(package_name, executable_name)
    assert path.is_file() and os.access(path, os.X_OK)
    assert path.parent == ament_env.prefix(package_name) / 'lib' / package_name

    # The console script must run on the venv interpreter (the one that has rclpy); the
    # ros_wheels_bootstrapper .pth in that venv re-executes it with LD_LIBRARY_PATH set.
    shebang = path.read_text().splitlines()[0]
    assert shebang.startswith('#!'), shebang
    interpreter = Path(shebang[2:].strip().split()[0])
    # (resolved: a checkout's .venv may be a symlink to a shared venv)
    assert interpreter.parent.resolve() == (Path(sys.prefix) / 'bin').resolve(), shebang
    assert os.access(interpreter, os.X_OK)

    # Like `ros2 run <pkg> <exe> --help` from a shell that sourced install/setup.sh.
    proc = ament_env.run(['bash', '-c', '. "$1/setup.sh" && exec "$2" --help', 'bash',
                          str(ament_env.install), str(path)], timeout=120, cwd='/')
    output, returncode = proc.stdout + proc.stderr, proc.returncode
    assert returncode == 0, f'`{executable_name} --help` exited {returncode}:\n{output}'
    assert 'usage' in output.lower(), output
