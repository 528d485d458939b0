"""The installed RViz configuration and team launch file describe the team they claim to."""

import importlib.util
from pathlib import Path
import sys
import types

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
LAUNCH_FILE = ROOT / 'launch' / 'team.launch.py'
RVIZ_FILE = ROOT / 'rviz' / 'landmarks.rviz'


def load_launch_file():
    """Import launch/team.launch.py as a module (it is no module of the package)."""
    spec = importlib.util.spec_from_file_location('team_launch', LAUNCH_FILE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# RViz -------------------------------------------------------------------------------------

def rviz_displays():
    """Return the RViz displays by topic (the Grid under None)."""
    document = yaml.safe_load(RVIZ_FILE.read_text())
    manager = document['Visualization Manager']
    assert manager['Global Options']['Fixed Frame'] == 'map'
    return {d.get('Topic', {}).get('Value'): d for d in manager['Displays']}


def test_rviz_config_shows_the_fused_map_and_every_default_robot():
    displays = rviz_displays()
    expected = {'/fused_markers': 'MarkerArray', '/fused_landmarks': 'PointCloud2',
                **{f'/robot{i}/landmark_markers': 'MarkerArray' for i in (1, 2, 3)}}
    for topic, kind in expected.items():
        assert displays[topic]['Class'] == f'rviz_default_plugins/{kind}', topic
        assert displays[topic]['Enabled'] is True
        assert displays[topic]['Topic']['Reliability Policy'] == 'Reliable'
    # The fuser's outputs are transient local: RViz must ask for them so to get the map.
    for topic in ('/fused_markers', '/fused_landmarks'):
        assert displays[topic]['Topic']['Durability Policy'] == 'Transient Local'
    assert displays['/robot1/landmark_markers']['Topic']['Durability Policy'] == 'Volatile'
    assert yaml.safe_load(RVIZ_FILE.read_text())['Panels'][0]['Class'] == \
        'rviz_common/Displays'


def test_rviz_robots_match_the_shipped_fuser_inputs():
    fuser = yaml.safe_load((ROOT / 'config' / 'fuser.yaml').read_text())
    inputs = fuser['/**/landmark_fuser']['ros__parameters']['input_topics']
    markers = {t for t in rviz_displays() if t and t.endswith('/landmark_markers')}
    assert markers == {t.replace('/landmarks', '/landmark_markers') for t in inputs}


# The launch file, with stand-ins for launch and launch_ros ---------------------------------

class Recorded:
    """A stand-in launch entity: keeps its arguments."""

    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class FakeConfiguration(Recorded):
    """LaunchConfiguration: ``perform`` reads the context dictionary."""

    def perform(self, context):
        return context[self.args[0]]


@pytest.fixture
def fake_launch(monkeypatch):
    """Replace launch and launch_ros by recorders; return the loaded launch file."""
    names = {
        'launch': ['LaunchDescription'],
        'launch.actions': ['DeclareLaunchArgument', 'OpaqueFunction'],
        'launch.conditions': ['IfCondition'],
        'launch.substitutions': ['PathJoinSubstitution'],
        'launch_ros': [],
        'launch_ros.actions': ['Node'],
        'launch_ros.substitutions': ['FindPackageShare'],
    }
    for module_name, classes in names.items():
        module = types.ModuleType(module_name)
        for class_name in classes:
            setattr(module, class_name, type(class_name, (Recorded,), {}))
        monkeypatch.setitem(sys.modules, module_name, module)
    sys.modules['launch.substitutions'].LaunchConfiguration = FakeConfiguration
    return load_launch_file()


def test_launch_file_declares_its_arguments(fake_launch):
    description = fake_launch.generate_launch_description()
    entities = description.args[0]
    arguments = {e.args[0]: e.kwargs for e in entities
                 if type(e).__name__ == 'DeclareLaunchArgument'}
    assert set(arguments) == {'robots', 'observer_params', 'fuser_params', 'rviz'}
    assert arguments['robots']['default_value'] == 'robot1 robot2 robot3'
    assert arguments['observer_params']['default_value'].args[0][1:] == ['config',
                                                                         'observer.yaml']
    assert arguments['fuser_params']['default_value'].args[0][1:] == ['config', 'fuser.yaml']
    assert all(a['description'] for a in arguments.values())
    rviz, = [e for e in entities if type(e).__name__ == 'Node']
    assert rviz.kwargs['executable'] == 'rviz2'
    assert rviz.kwargs['arguments'][1].args[0][1:] == ['rviz', 'landmarks.rviz']
    assert any(type(e).__name__ == 'OpaqueFunction' for e in entities)


def test_launch_file_builds_one_observer_per_robot_and_one_fuser(fake_launch):
    description = fake_launch.generate_launch_description()
    team, = [e for e in description.args[0] if type(e).__name__ == 'OpaqueFunction']
    context = {'robots': ' alpha, /beta  gamma/ ', 'observer_params': '/p/observer.yaml',
               'fuser_params': '/p/fuser.yaml'}
    nodes = team.kwargs['function'](context)
    observers, fuser = nodes[:-1], nodes[-1]
    assert [n.kwargs['namespace'] for n in observers] == ['alpha', 'beta', 'gamma']
    for node in observers:
        assert node.kwargs['package'] == 'landmark_ros'
        assert node.kwargs['executable'] == node.kwargs['name'] == 'landmark_observer'
        assert node.kwargs['parameters'] == ['/p/observer.yaml']
    assert fuser.kwargs['executable'] == fuser.kwargs['name'] == 'landmark_fuser'
    assert 'namespace' not in fuser.kwargs
    assert fuser.kwargs['parameters'] == [
        '/p/fuser.yaml',
        {'input_topics': ['/alpha/landmarks', '/beta/landmarks', '/gamma/landmarks']}]


@pytest.mark.parametrize('robots', ['', ' , ', 'a b a'])
def test_launch_file_refuses_no_robot_or_a_repeated_one(fake_launch, robots):
    with pytest.raises(ValueError, match='robots'):
        fake_launch.robot_names(robots)


# The launch file with the real launch_ros ------------------------------------------------

def test_launch_file_with_launch_ros():
    try:
        import launch
        import launch_ros  # noqa: F401
    except ImportError as error:
        pytest.skip(f'launch_ros cannot be imported ({error}): it is not on PyPI; the '
                    'stand-in tests above check the launch file')
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch_ros.actions import Node
    description = load_launch_file().generate_launch_description()
    arguments = {e.name for e in description.entities if isinstance(e, DeclareLaunchArgument)}
    assert arguments == {'robots', 'observer_params', 'fuser_params', 'rviz'}
    context = launch.LaunchContext()
    context.launch_configurations.update({
        'robots': 'robot1 robot2', 'observer_params': '/p/observer.yaml',
        'fuser_params': '/p/fuser.yaml'})
    team, = [e for e in description.entities if isinstance(e, OpaqueFunction)]
    nodes = team.execute(context)
    assert all(isinstance(n, Node) for n in nodes)
    assert [n.node_executable for n in nodes] == ['landmark_observer'] * 2 + ['landmark_fuser']
    assert {n.node_package for n in nodes} == {'landmark_ros'}
