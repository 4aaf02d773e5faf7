"""Packaging: one version, complete dependencies, the licence, the installed config files and the
Makefile's interpreter choice.  Static checks of the checkout (no build, no ROS)."""
import ast
import os
import re
import runpy
import shutil
import subprocess
import sys
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

import sep_control
import sep_estimator
import sep_plant

REPO_ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ('sep_plant', 'sep_estimator', 'sep_control')

# Third-party modules the packages import -> the requirement that provides them (a setup.py
# install_requires entry, or an extra written 'extra:<name>').
MODULE_REQUIREMENT = {
    'numpy': 'numpy', 'scipy': 'scipy', 'yaml': 'PyYAML', 'matplotlib': 'matplotlib',
    'rosbags': 'rosbags', 'tqdm': 'tqdm', 'threadpoolctl': 'threadpoolctl', 'osqp': 'osqp',
    'lz4': 'lz4', 'backports': 'backports.zstd',
    'dask': 'extra:dask', 'distributed': 'extra:dask', 'fmpy': 'extra:fmu',
}
# Imported only inside a guard, never required: the module -> why.
OPTIONAL_MODULES = {
    'cupy': 'plants on a GPU (docs/gpu.md), imported only for device=cuda',
    'compression': 'the standard library from Python 3.14 (backports.zstd before)',
}
# ROS packages: from ROS (package.xml exec_depend), never from PyPI (install_requires).
ROS_MODULE = re.compile(r'^(rclpy|ament_index_python|builtin_interfaces|rcl_interfaces|\w+_msgs)$')
# install_requires entry -> how a native ROS install gets it: a rosdep key in package.xml, or
# requirements-ros.txt (no rosdep key), or 'rosbags' (a dependency of rosbags).
ROSDEP_KEY = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'pyyaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm', 'rosbags': 'python3-rosbags-pip',
}
VIA_ROSBAGS = {'lz4', 'backports-zstd'}


def setup_kwargs(pkg: str, monkeypatch) -> dict:
    """The keyword arguments <pkg>/setup.py passes to setuptools.setup (run, setup() captured)."""
    import setuptools

    captured = {}
    monkeypatch.setattr(setuptools, 'setup', lambda **kw: captured.update(kw))
    monkeypatch.chdir(REPO_ROOT / pkg)
    runpy.run_path(str(REPO_ROOT / pkg / 'setup.py'), run_name='__main__')
    return captured


def literal_setup_version(pkg: str) -> str:
    """The version literal of <pkg>/setup.py, read without running it."""
    tree = ast.parse((REPO_ROOT / pkg / 'setup.py').read_text())
    found = [node.value.value for node in ast.walk(tree)
             if isinstance(node, ast.Assign) and [getattr(t, 'id', None) for t in node.targets] == ['VERSION']
             and isinstance(node.value, ast.Constant)]
    assert len(found) == 1, f'{pkg}/setup.py: expected one literal VERSION = "..."'
    return found[0]


def package_xml(pkg: str) -> ET.Element:
    return ET.parse(REPO_ROOT / pkg / 'package.xml').getroot()


def imported_modules(pkg: str) -> dict[str, set[str]]:
    """Top-level modules imported by the package's modules (absolute imports), each with the
    files that import it."""
    found: dict[str, set[str]] = {}
    for path in sorted((REPO_ROOT / pkg / pkg).rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            else:
                continue
            for name in names:
                found.setdefault(name.split('.')[0], set()).add(str(path.relative_to(REPO_ROOT)))
    return found


def third_party(modules) -> list[str]:
    return sorted(m for m in modules if m not in sys.stdlib_module_names and m not in PACKAGES)


# ------------------------------------------------------------------------------ one version
def test_one_version_everywhere():
    """sep_plant.__version__ is the version; every literal copy equals it."""
    version = sep_plant.__version__
    assert re.fullmatch(r'\d+\.\d+\.\d+', version), version
    assert sep_estimator.__version__ == version and sep_control.__version__ == version
    for pkg in PACKAGES:
        assert literal_setup_version(pkg) == version, f'{pkg}/setup.py'
        assert package_xml(pkg).findtext('version') == version, f'{pkg}/package.xml'
    # the example plant installs on its own; if it ever pins sep, the pin is this version
    project = tomllib.loads((REPO_ROOT / 'examples/burgers/pyproject.toml').read_text())['project']
    for dep in project.get('dependencies', []):
        req = Requirement(dep)
        if canonicalize_name(req.name) in {canonicalize_name(p) for p in PACKAGES}:
            assert req.specifier.contains(version), f'examples/burgers/pyproject.toml: {dep}'


def test_version_defined_once():
    """Only sep_plant assigns __version__; the other packages import it."""
    for pkg in PACKAGES:
        tree = ast.parse((REPO_ROOT / pkg / pkg / '__init__.py').read_text())
        assigns = [n for n in ast.walk(tree) if isinstance(n, ast.Assign)
                   and any(getattr(t, 'id', None) == '__version__' for t in n.targets)]
        assert len(assigns) == (1 if pkg == 'sep_plant' else 0), pkg


def test_setup_py_uses_its_literal_version(monkeypatch):
    for pkg in PACKAGES:
        kw = setup_kwargs(pkg, monkeypatch)
        assert kw['name'] == pkg and kw['version'] == sep_plant.__version__, pkg
        # the three packages require each other at exactly this version
        for spec in kw['install_requires']:
            req = Requirement(spec)
            if req.name in PACKAGES:
                assert str(req.specifier) == f'=={sep_plant.__version__}', (pkg, spec)


# ------------------------------------------------------------------------------ dependencies
def test_install_requires_cover_the_imports(monkeypatch):
    """Every third-party module a package imports is in its install_requires (or an extra, or a
    documented optional import); ROS packages are package.xml dependencies, never PyPI ones."""
    for pkg in PACKAGES:
        kw = setup_kwargs(pkg, monkeypatch)
        required = {canonicalize_name(Requirement(r).name) for r in kw['install_requires']}
        extras = set(kw.get('extras_require', {}))
        exec_depends = {e.text for e in package_xml(pkg).iter('exec_depend')}
        imports = imported_modules(pkg)
        for module in third_party(imports):
            where = sorted(imports[module])
            if ROS_MODULE.match(module):
                assert module in exec_depends, f'{pkg}/package.xml lacks {module} ({where})'
                assert canonicalize_name(module) not in required, f'{pkg}: {module} is from ROS'
            elif module in OPTIONAL_MODULES:
                continue
            else:
                assert module in MODULE_REQUIREMENT, f'{pkg} imports {module} ({where}): classify it here'
                need = MODULE_REQUIREMENT[module]
                if need.startswith('extra:'):
                    assert need[6:] in extras, f'{pkg}/setup.py: extra {need[6:]!r} for {module}'
                else:
                    assert canonicalize_name(need) in required, f'{pkg}/setup.py lacks {need} ({where})'
        assert not any(r.startswith(('rclpy', 'ros-')) for r in required), pkg
        # sep_estimator and sep_control need the packages below them
        for dep in PACKAGES[:PACKAGES.index(pkg)]:
            if dep in imports:
                assert canonicalize_name(dep) in required and dep in exec_depends, (pkg, dep)


def test_every_requirement_reaches_a_native_ros_install(monkeypatch):
    """A native Jazzy install gets each run-time requirement from rosdep (package.xml key) or from
    requirements-ros.txt (no rosdep key); pins there equal requirements.txt's."""
    pins = pinned('requirements.txt')
    ros_pins = pinned('requirements-ros.txt')
    for name, line in ros_pins.items():
        assert pins.get(name) == line, f'requirements-ros.txt: {line} != requirements.txt'
    for pkg in PACKAGES:
        kw = setup_kwargs(pkg, monkeypatch)
        exec_depends = {e.text for e in package_xml(pkg).iter('exec_depend')}
        for spec in kw['install_requires']:
            name = canonicalize_name(Requirement(spec).name)
            if name in {canonicalize_name(p) for p in PACKAGES}:
                continue
            # lz4 and backports.zstd come with (pinned) rosbags
            assert name in pins or name in VIA_ROSBAGS, f'{pkg}: {name} is not pinned in requirements.txt'
            if name in ROSDEP_KEY:
                assert ROSDEP_KEY[name] in exec_depends, f'{pkg}/package.xml lacks {ROSDEP_KEY[name]}'
            elif name in VIA_ROSBAGS:
                assert 'python3-rosbags-pip' in exec_depends, pkg
            else:
                assert name in ros_pins, f'{name} ({pkg}): no rosdep key, so requirements-ros.txt'
        for extra in kw.get('extras_require', {}).values():
            for spec in extra:
                name = canonicalize_name(Requirement(spec).name)
                assert name in pins, f'{pkg}: extra {spec} is not pinned in requirements.txt'


def pinned(filename: str) -> dict[str, str]:
    """{canonical name: 'name[extras]==version'} of a requirements file (every line pinned)."""
    out = {}
    for line in (REPO_ROOT / filename).read_text().splitlines():
        line = line.split('#', 1)[0].strip()
        if line:
            req = Requirement(line)
            assert len(req.specifier) == 1 and str(req.specifier).startswith('=='), f'{filename}: {line}'
            out[canonicalize_name(req.name)] = line
    return out


# ------------------------------------------------------------------------------ licence, data
def test_apache_license():
    text = (REPO_ROOT / 'LICENSE').read_text()
    assert text.lstrip().startswith('Apache License') and 'Version 2.0, January 2004' in text
    assert 'END OF TERMS AND CONDITIONS' in text and len(text.splitlines()) > 190   # the full text
    for pkg in PACKAGES:
        assert package_xml(pkg).findtext('license') == 'Apache-2.0', pkg


def test_config_files_ship_with_their_package(monkeypatch):
    """The nodes' parameter files live in <pkg>/config and are installed to share/<pkg>/config."""
    assert not (REPO_ROOT / 'ros_ws' / 'config').exists()
    for pkg in PACKAGES:
        sources = sorted(f'config/{p.name}' for p in (REPO_ROOT / pkg / 'config').glob('*.yaml'))
        assert sources, pkg
        data = dict(setup_kwargs(pkg, monkeypatch)['data_files'])
        assert sorted(data[f'share/{pkg}/config']) == sources, pkg


def test_sep_console_script(monkeypatch):
    scripts = setup_kwargs('sep_control', monkeypatch)['entry_points']['console_scripts']
    assert 'sep = sep_control.cli.main:main' in scripts
    names = {s.split('=')[0].strip() for s in scripts}
    assert {'lqr', 'lqg', 'record', 'design', 'evaluate', 'validate', 'analyze', 'demo'} <= names


# ------------------------------------------------------------------------------ Makefile
FAKE_PYTHON = """#!/bin/sh
# a stand-in interpreter: reports version {version}, logs every call, `-m venv DIR` makes DIR
echo "$*" >> "{log}"
case "$1 $2" in
  "-m venv") mkdir -p "$3/bin" && cp "$0" "$3/bin/python" ;;
  "-c "*) echo "{version}" ;;
esac
"""


def fake_python(path: Path, version: str) -> Path:
    path.write_text(FAKE_PYTHON.format(version=version, log=path.with_suffix('.log')))
    path.chmod(0o755)
    return path


MAKE = shutil.which('make') or 'make'


@pytest.fixture
def scratch_checkout(tmp_path):
    """The Makefile and the files its venv rule depends on, in an empty folder (no .venv)."""
    root = tmp_path / 'checkout'
    (root / 'examples/burgers').mkdir(parents=True)
    for rel in ('Makefile', 'requirements.txt', 'requirements-controlgym.txt', 'examples/burgers/pyproject.toml'):
        (root / rel).write_bytes((REPO_ROOT / rel).read_bytes())
    return root


def make(root: Path, *args: str, path: str = '/usr/bin:/bin') -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ('PYTHON', 'MAKEFLAGS', 'MFLAGS')}
    env['PATH'] = path
    return subprocess.run([MAKE, '--no-print-directory', '-C', str(root), *args], env=env,
                          capture_output=True, text=True, timeout=60, stdin=subprocess.DEVNULL)


@pytest.mark.parametrize('version', ['3.11', '3.12'])
def test_make_venv_accepts_python(scratch_checkout, tmp_path, version):
    py = fake_python(tmp_path / f'python{version}', version)
    proc = make(scratch_checkout, 'venv', f'PYTHON={py}')
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f'-m venv {scratch_checkout}/.venv' in py.with_suffix('.log').read_text()
    assert f'creating {scratch_checkout}/.venv with {py} (Python {version})' in proc.stdout


@pytest.mark.parametrize('version,needle', [('3.10', 'is Python 3.10'), ('3.13', 'is Python 3.13')])
def test_make_venv_refuses_an_untested_python_at_once(scratch_checkout, tmp_path, version, needle):
    py = fake_python(tmp_path / f'python{version}', version)
    proc = make(scratch_checkout, 'venv', f'PYTHON={py}')
    assert proc.returncode != 0
    assert needle in proc.stderr and 'tested on Python 3.11 3.12' in proc.stderr, proc.stderr
    assert 'PYTHON=python3.12 make' in proc.stderr and 'requirements-ros.txt' in proc.stderr
    assert '-m venv' not in py.with_suffix('.log').read_text()     # nothing created
    assert not (scratch_checkout / '.venv').exists()


def test_make_venv_without_any_supported_python(scratch_checkout, tmp_path):
    bare = tmp_path / 'bin'
    bare.mkdir()
    proc = make(scratch_checkout, 'venv', path=str(bare))
    assert proc.returncode != 0
    assert 'no python3.11 or python3.12 found' in proc.stderr, proc.stderr
    assert not (scratch_checkout / '.venv').exists()


def test_make_venv_refuses_to_mix_interpreters(scratch_checkout, tmp_path):
    """PYTHON given for an existing venv of another version: recreate it, do not mix."""
    old = fake_python(tmp_path / 'python3.11', '3.11')
    assert make(scratch_checkout, 'venv', f'PYTHON={old}').returncode == 0
    new = fake_python(tmp_path / 'python3.12', '3.12')
    proc = make(scratch_checkout, 'venv', f'PYTHON={new}')
    assert proc.returncode != 0 and 'make distclean' in proc.stderr, proc.stderr


def test_make_venv_with_a_python_that_does_not_run(scratch_checkout, tmp_path):
    proc = make(scratch_checkout, 'venv', f'PYTHON={tmp_path / "missing" / "python3.12"}')
    assert proc.returncode != 0 and 'does not run' in proc.stderr, proc.stderr
    assert 'PYTHON=python3.12 make' in proc.stderr and not (scratch_checkout / '.venv').exists()
