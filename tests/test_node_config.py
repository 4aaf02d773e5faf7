"""The nodes' parameter files, as installed (share/<pkg>/config/ of the colcon install, the
`$(ros2 pkg prefix <pkg>)/share/<pkg>/config/...` a user passes), load with --params-file and
reach the nodes."""
import json
import signal
from pathlib import Path

import pytest

from node_harness import launcher, small_case  # noqa: F401

pytestmark = pytest.mark.ros
REPO_ROOT = Path(__file__).resolve().parent.parent
# parameter file -> the package that ships it (sources in <pkg>/config/)
CONFIG_FILES = {'plant.yaml': 'sep_plant', 'plant_realtime.yaml': 'sep_plant',
                'estimator.yaml': 'sep_estimator', 'lqr.yaml': 'sep_control', 'lqg.yaml': 'sep_control'}


def installed(install, name: str) -> Path:
    """share/<pkg>/config/<name> of the colcon install (tests/conftest.ColconInstall)."""
    pkg = CONFIG_FILES[name]
    return install.prefix(pkg) / 'share' / pkg / 'config' / name


def test_config_files_installed_unchanged(colcon_install):
    """Every package's config/*.yaml is installed, byte for byte, and nothing else."""
    for pkg in set(CONFIG_FILES.values()):
        sources = {p.name for p in (REPO_ROOT / pkg / 'config').glob('*.yaml')}
        assert sources == {n for n, owner in CONFIG_FILES.items() if owner == pkg}, pkg
        shipped = {p.name for p in (colcon_install.prefix(pkg) / 'share' / pkg / 'config').iterdir()}
        assert shipped == sources, pkg
        for name in sources:
            assert installed(colcon_install, name).read_bytes() == \
                (REPO_ROOT / pkg / 'config' / name).read_bytes(), name


def test_plant_params_files(launcher, small_case, tmp_path):
    install = launcher.install
    p = launcher.start('plant', '--ros-args', '--params-file', str(installed(install, 'plant.yaml')),
                       '--params-file', str(installed(install, 'plant_realtime.yaml')),
                       params={'scenario_file': small_case.scenario_file, 'wait_for_subscribers': 0,
                               'real_time_factor': 200.0, 'summary_file': tmp_path / 'p.json'})
    assert p.wait(60) == 0, p.output()
    summ = json.loads((tmp_path / 'p.json').read_text())
    assert summ['mode'] == 'realtime' and summ['real_time_factor'] == 200.0
    assert summ['deadline_misses'] == small_case.n_steps      # nobody answered: all held


@pytest.mark.parametrize('exe,files', [('lqg', ['lqg.yaml']), ('estimator', ['estimator.yaml']),
                                       ('lqr', ['lqr.yaml'])])
def test_controller_params_files(launcher, small_case, exe, files):
    args = ['--ros-args']
    for f in files:
        args += ['--params-file', str(installed(launcher.install, f))]
    p = launcher.start(exe, *args, params={'design_file': small_case.design_file})
    out = ''
    import time
    t_end = time.monotonic() + 30
    while time.monotonic() < t_end and p.returncode is None:
        out = p.output()
        if f'design file {small_case.design_file}' in out:
            break
        time.sleep(0.1)
    assert f'design file {small_case.design_file}' in out, out
    if exe == 'lqr':
        assert 'estimate_timeout_s 0.5' in out
    p.signal(signal.SIGINT)
    assert p.wait(15) == 130, p.output()
