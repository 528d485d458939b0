"""Build the package with colcon into a scratch workspace and check the install."""

import configparser
import os
from pathlib import Path
import shutil
import subprocess
import sys

import pytest

# Console scripts (entry_points in setup.py) that must be installed to
# lib/landmark_ros/. Add a node's name here when adding it to setup.py: the
# test below fails if the two lists differ.
EXPECTED_EXECUTABLES = [
    'landmark_bag',
    'landmark_fuser',
    'landmark_localizer',
    'landmark_mrclam',
    'landmark_observer',
    'landmark_sim',
]

PACKAGE = 'landmark_ros'
REPO_ROOT = Path(__file__).resolve().parents[1]
COLCON = Path(sys.executable).parent / 'colcon'
# Outputs colcon (or setup.py) could drop into the source tree.
POLLUTION = ('build', 'install', 'log', PACKAGE + '.egg-info')

pytestmark = pytest.mark.slow


@pytest.fixture(scope='module')
def install_prefix(tmp_path_factory):
    """Run `colcon build` on the repo into a tmp workspace; return the package prefix."""
    if not COLCON.exists():
        colcon = shutil.which('colcon')
        if colcon is None:
            pytest.skip('colcon is not installed (pip install colcon-common-extensions)')
    else:
        colcon = str(COLCON)

    ws = tmp_path_factory.mktemp('colcon_ws')
    existed_before = {name for name in POLLUTION if (REPO_ROOT / name).exists()}
    env = dict(os.environ, COLCON_HOME=str(ws / 'colcon_home'))  # ignore user defaults
    cmd = [
        colcon, '--log-base', str(ws / 'log'),
        'build',
        '--base-paths', str(REPO_ROOT),
        '--packages-select', PACKAGE,
        '--build-base', str(ws / 'build'),
        '--install-base', str(ws / 'install'),
        '--event-handlers', 'console_cohesion+', 'console_start_end-',
    ]
    proc = subprocess.run(
        cmd, cwd=ws, env=env, capture_output=True, text=True, timeout=300)

    # Whatever happened, do not leave build side effects in the source tree.
    left_behind = sorted(
        name for name in POLLUTION
        if name not in existed_before and (REPO_ROOT / name).exists())
    for name in left_behind:
        shutil.rmtree(REPO_ROOT / name, ignore_errors=True)

    assert proc.returncode == 0, (
        'colcon build failed:\n%s\n%s\n%s' % (' '.join(cmd), proc.stdout, proc.stderr))
    assert not left_behind, 'colcon build wrote into the source tree: %s' % left_behind
    return ws / 'install' / PACKAGE


def test_ament_index_marker(install_prefix):
    marker = install_prefix / 'share/ament_index/resource_index/packages' / PACKAGE
    assert marker.is_file()


def test_package_xml_installed(install_prefix):
    assert (install_prefix / 'share' / PACKAGE / 'package.xml').is_file()


def test_config_files_installed(install_prefix):
    source = {p.name for p in (REPO_ROOT / 'config').glob('*.yaml')}
    config_dir = install_prefix / 'share' / PACKAGE / 'config'
    installed = {p.name for p in config_dir.glob('*.yaml')} if config_dir.is_dir() else set()
    assert installed == source


@pytest.mark.parametrize('folder, pattern', [('launch', '*.launch.py'), ('rviz', '*.rviz')])
def test_launch_and_rviz_files_installed(install_prefix, folder, pattern):
    source = {p.name for p in (REPO_ROOT / folder).glob(pattern)}
    assert source, f'no {folder}/{pattern} in the repository'
    target = install_prefix / 'share' / PACKAGE / folder
    installed = {p.name for p in target.glob(pattern)} if target.is_dir() else set()
    assert installed == source


def _declared_console_scripts(install_prefix):
    """Console scripts from the entry_points.txt colcon installed (none: no file)."""
    names = set()
    for ep_file in install_prefix.glob('lib/python*/site-packages/%s-*/entry_points.txt'
                                       % PACKAGE):
        parser = configparser.ConfigParser(delimiters=('=',))
        parser.optionxform = str
        parser.read(ep_file)
        if parser.has_section('console_scripts'):
            names.update(parser.options('console_scripts'))
    return names


def test_declared_console_scripts_match_expected(install_prefix):
    assert len(EXPECTED_EXECUTABLES) == len(set(EXPECTED_EXECUTABLES))
    assert _declared_console_scripts(install_prefix) == set(EXPECTED_EXECUTABLES), (
        'setup.py console_scripts and EXPECTED_EXECUTABLES in %s differ'
        % Path(__file__).name)


def test_executables_installed(install_prefix):
    lib_dir = install_prefix / 'lib' / PACKAGE
    for name in EXPECTED_EXECUTABLES:
        exe = lib_dir / name
        assert exe.is_file(), '%s not installed' % exe
        assert os.access(exe, os.X_OK), '%s is not executable' % exe
    installed = {p.name for p in lib_dir.iterdir()} if lib_dir.is_dir() else set()
    assert installed == set(EXPECTED_EXECUTABLES)
