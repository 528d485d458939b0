"""
The RViz configuration and the team launch file describe the team they claim to.

The launch file with stand-ins for launch and launch_ros (no ROS tools needed), and with
the real ones when installed; ``test/launch`` runs it with ``ros2 launch``.
"""

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
        'launch.actions': ['DeclareLaunchArgument', 'OpaqueFunction', 'Shutdown'],
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


ARGUMENTS = {'robots', 'observer_params', 'fuser_params', 'sim', 'sim_params', 'fusion',
             'rviz', 'rviz_config', 'localize', 'localizer_params'}


@pytest.fixture
def context(tmp_path):
    """Launch arguments as ``ros2 launch`` performs them, with parameter files that exist."""
    values = {'robots': ' alpha, /beta  gamma/ ', 'sim': 'false', 'fusion': '',
              'rviz': 'false', 'rviz_config': '/p/landmarks.rviz', 'localize': 'false',
              'localizer_params': ''}
    for name in ('observer_params', 'fuser_params', 'sim_params'):
        path = tmp_path / f'{name}.yaml'
        path.write_text('/**:\n  ros__parameters: {}\n')
        values[name] = str(path)
    return values


def start(fake_launch, context):
    """Return the actions the launch description's one OpaqueFunction starts."""
    description = fake_launch.generate_launch_description()
    team, = [e for e in description.args[0] if type(e).__name__ == 'OpaqueFunction']
    return team.kwargs['function'](context)


def test_launch_file_declares_its_arguments(fake_launch):
    description = fake_launch.generate_launch_description()
    entities = description.args[0]
    arguments = {e.args[0]: e.kwargs for e in entities
                 if type(e).__name__ == 'DeclareLaunchArgument'}
    assert set(arguments) == ARGUMENTS == set(fake_launch.ARGUMENTS)
    assert arguments['robots']['default_value'] == 'robot1 robot2 robot3'
    for name, file in (('observer_params', 'observer.yaml'), ('fuser_params', 'fuser.yaml'),
                       ('sim_params', 'sim.yaml')):
        assert arguments[name]['default_value'].args[0][1:] == ['config', file]
    assert arguments['rviz_config']['default_value'].args[0][1:] == ['rviz', 'landmarks.rviz']
    assert (arguments['sim']['default_value'], arguments['rviz']['default_value'],
            arguments['fusion']['default_value']) == ('false', 'false', '')
    assert all(a['description'] for a in arguments.values())
    # Nothing starts but through the one action that checks the arguments first.
    assert [type(e).__name__ for e in entities if type(e).__name__ != 'DeclareLaunchArgument'] \
        == ['OpaqueFunction']


def test_launch_file_builds_one_observer_per_robot_and_one_fuser(fake_launch, context):
    nodes = start(fake_launch, context)
    observers, fuser = nodes[:-1], nodes[-1]
    assert [n.kwargs['namespace'] for n in observers] == ['alpha', 'beta', 'gamma']
    for node in observers:
        assert node.kwargs['package'] == 'landmark_ros'
        assert node.kwargs['executable'] == node.kwargs['name'] == 'landmark_observer'
        assert node.kwargs['parameters'] == [context['observer_params']]
    assert fuser.kwargs['executable'] == fuser.kwargs['name'] == 'landmark_fuser'
    assert 'namespace' not in fuser.kwargs
    assert fuser.kwargs['parameters'] == [context['fuser_params'], {
        parameter: [f'/{robot}/{topic}' for robot in ('alpha', 'beta', 'gamma')]
        for parameter, topic in fake_launch.FUSER_INPUTS.items()}]
    # A team process failing once started stops the launch (no orphan half team).
    assert all(n.kwargs['on_exit'] is fake_launch.on_failure for n in nodes)


@pytest.mark.parametrize('robots', [['robot1'], ['robot1', 'robot2', 'robot3', 'robot4'],
                                    ['alpha', 'beta'], ['a/b', 'c']])
def test_every_per_robot_fuser_input_follows_robots(fake_launch, context, robots):
    context['robots'] = ' '.join(robots)
    fuser = start(fake_launch, context)[-1]
    overrides = fuser.kwargs['parameters'][1]
    assert set(overrides) == set(fake_launch.FUSER_INPUTS) >= {'input_topics'}
    for parameter, topics in overrides.items():
        assert topics == [f'/{robot}/{fake_launch.FUSER_INPUTS[parameter]}' for robot in robots]


def test_fuser_yaml_lists_no_per_robot_topic_the_launch_file_leaves_alone(fake_launch):
    # Every *_topics parameter of the shipped fuser.yaml is one the launch file rebuilds
    # from robots: a renamed or new per-robot parameter must be added to FUSER_INPUTS.
    fuser = yaml.safe_load((ROOT / 'config' / 'fuser.yaml').read_text())
    parameters = fuser['/**/landmark_fuser']['ros__parameters']
    assert {name for name in parameters if name.endswith('_topics')} == \
        set(fake_launch.FUSER_INPUTS)


def test_sim_starts_the_named_robots(fake_launch, context):
    context.update(sim='true', robots='robot1 scout robot3 robot4')
    sim = start(fake_launch, context)[-1]
    assert sim.kwargs['executable'] == sim.kwargs['name'] == 'landmark_sim'
    assert sim.kwargs['parameters'] == [context['sim_params'], {'robots': 4}]
    topics = ('pose', 'true_pose', 'observations', 'odometry')
    assert sorted(sim.kwargs['remappings']) == sorted(
        (f'robot2/{t}', f'/scout/{t}') for t in topics)
    # The observers take the simulator's streams as reliable, transient-local inputs.
    scout = start(fake_launch, context)[1]
    assert scout.kwargs['parameters'] == [context['observer_params'], {
        f'qos_overrides./scout/{topic}.subscription.{policy}': value
        for topic in ('observations', 'pose')
        for policy, value in (('reliability', 'reliable'), ('durability', 'transient_local'))}]


def test_localize_starts_a_localizer_per_robot_and_moves_the_sim_pose(fake_launch, context):
    context.update(sim='true', localize='true', robots='alpha beta')
    nodes = start(fake_launch, context)
    localizers = [n for n in nodes if n.kwargs.get('executable') == 'landmark_localizer']
    assert sorted(n.kwargs['namespace'] for n in localizers) == ['alpha', 'beta']
    sim = nodes[-1] if nodes[-1].kwargs['executable'] == 'landmark_sim' else [
        n for n in nodes if n.kwargs.get('executable') == 'landmark_sim'][0]
    assert ('robot1/pose', '/alpha/sim_pose') in sim.kwargs['remappings']
    # sim_pose has no reader: the simulator waits for the localizers' odometry, not for it
    waits = sim.kwargs['parameters'][1]
    assert waits['wait_for_pose_subscribers'] is False
    assert waits['wait_for_odometry_subscribers'] is True
    # The observer's pose is the localizer's (volatile): only its observations are replayed.
    observer = nodes[0]
    assert observer.kwargs['parameters'][1] == {
        'qos_overrides./alpha/observations.subscription.reliability': 'reliable',
        'qos_overrides./alpha/observations.subscription.durability': 'transient_local'}
    replayed = localizers[0].kwargs['parameters'][-1]
    assert sorted(replayed) == sorted(
        f'qos_overrides./{localizers[0].kwargs["namespace"]}/{topic}.subscription.{policy}'
        for topic in ('odometry', 'observations') for policy in ('reliability', 'durability'))
    # The loop's rows carry the localizers' slow pose errors: no change detection.
    fuser, = [n for n in nodes if n.kwargs.get('executable') == 'landmark_fuser']
    assert fuser.kwargs['parameters'][1]['move_false_alarm_rate'] == 0.0
    context.update(localize='false')
    fuser, = [n for n in start(fake_launch, context)
              if n.kwargs.get('executable') == 'landmark_fuser']
    assert 'move_false_alarm_rate' not in fuser.kwargs['parameters'][1]    # the file's


def test_fusion_argument_overrides_the_file(fake_launch, context):
    assert 'fusion' not in start(fake_launch, context)[-1].kwargs['parameters'][1]
    context['fusion'] = 'covariance_intersection'
    fuser = start(fake_launch, context)[-1]
    assert fuser.kwargs['parameters'][1]['fusion'] == 'covariance_intersection'


@pytest.mark.parametrize('change, message', [
    ({'robots': ' , '}, 'robots: give at least one robot name'),
    ({'robots': 'a b a'}, 'names a robot twice'),
    ({'observer_params': '/no/such.yaml'}, 'observer_params: no such parameter file'),
    ({'fuser_params': '/no/such.yaml'}, 'fuser_params: no such parameter file'),
    ({'sim': 'true', 'sim_params': '/no/such.yaml'}, 'sim_params: no such parameter file'),
    ({'fusion': 'average'}, "fusion: 'average' is not one of"),
    ({'sim': 'yes'}, 'sim: expected true or false'),
    ({'rviz': '1'}, 'rviz: expected true or false'),
])
def test_bad_arguments_fail_before_any_node(fake_launch, context, change, message):
    context.update(change)
    with pytest.raises(fake_launch.TeamError, match=message):
        start(fake_launch, context)


def test_sim_params_unchecked_without_sim(fake_launch, context):
    context['sim_params'] = '/no/such.yaml'
    assert len(start(fake_launch, context)) == 4


@pytest.mark.parametrize('text', ['a: [1, 2', 'just a string', '\x00'])
def test_a_params_file_that_is_no_yaml_mapping_fails(fake_launch, context, tmp_path, text):
    broken = tmp_path / 'broken.yaml'
    broken.write_text(text)
    context['fuser_params'] = str(broken)
    with pytest.raises(fake_launch.TeamError, match=f'fuser_params: .*{broken}') as error:
        start(fake_launch, context)
    assert '\n' not in str(error.value)


def test_rviz_needs_rviz2_installed(fake_launch, context, monkeypatch):
    context['rviz'] = 'true'
    monkeypatch.setattr(fake_launch, 'rviz_installed', lambda: False)
    with pytest.raises(fake_launch.TeamError, match="rviz: package 'rviz2' is not installed"):
        start(fake_launch, context)
    monkeypatch.setattr(fake_launch, 'rviz_installed', lambda: True)
    rviz = start(fake_launch, context)[-1]
    assert rviz.kwargs['executable'] == 'rviz2'
    assert rviz.kwargs['arguments'] == ['-d', context['rviz_config']]


def test_rviz_installed_asks_the_ament_index(tmp_path, monkeypatch):
    pytest.importorskip('ament_index_python')
    launch_file = load_launch_file_real_or_skip()
    monkeypatch.delenv('AMENT_PREFIX_PATH', raising=False)
    assert launch_file.rviz_installed() is False
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(tmp_path))
    assert launch_file.rviz_installed() is False
    index = tmp_path / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    (index / 'rviz2').write_text('')
    assert launch_file.rviz_installed() is False        # the package without its program
    program = tmp_path / 'lib' / 'rviz2' / 'rviz2'
    program.parent.mkdir(parents=True)
    program.write_text('#!/bin/sh\n')
    program.chmod(0o755)
    assert launch_file.rviz_installed() is True


class Exited:
    """A stand-in ProcessExited event."""

    process_name = 'landmark_fuser-4'

    def __init__(self, returncode):
        self.returncode = returncode


class Context:
    """A stand-in LaunchContext."""

    def __init__(self, is_shutdown):
        self.is_shutdown = is_shutdown


def test_a_team_process_failing_shuts_the_launch_down(fake_launch):
    shutdown, = fake_launch.on_failure(Exited(2), Context(False))
    assert type(shutdown).__name__ == 'Shutdown'
    assert 'landmark_fuser-4 exited with code 2' in shutdown.kwargs['reason']
    assert fake_launch.on_failure(Exited(0), Context(False)) is None
    assert fake_launch.on_failure(Exited(-2), Context(True)) is None


@pytest.mark.parametrize('robots', ['', ' , ', 'a b a'])
def test_launch_file_refuses_no_robot_or_a_repeated_one(fake_launch, robots):
    with pytest.raises(ValueError, match='robots'):
        fake_launch.robot_names(robots)


def test_the_observer_publishes_what_the_fuser_is_given():
    # FUSER_INPUTS names the observer's output topics; an observer node says which.
    from landmark_ros.nodes.observer import LandmarkObserver
    from rosutil import RosEnv
    launch_file = load_launch_file_real_or_skip()
    env = RosEnv()
    try:
        node = env.add(LandmarkObserver(context=env.context, namespace='/robot7'))
        published = {publisher.topic_name for publisher in node.publishers}
    finally:
        env.close()
    assert {f'/robot7/{topic}' for topic in launch_file.FUSER_INPUTS.values()} <= published


# The launch file with the real launch_ros ------------------------------------------------

def load_launch_file_real_or_skip():
    """Return the launch file loaded with the real launch and launch_ros (or skip)."""
    try:
        import launch  # noqa: F401
        import launch_ros  # noqa: F401
    except ImportError as error:
        pytest.skip(f'launch_ros cannot be imported ({error}): it is not on PyPI '
                    '(../shared/ros-tools installs it); the stand-in tests check the file')
    return load_launch_file()


def test_launch_file_with_launch_ros(context):
    launch_file = load_launch_file_real_or_skip()
    import launch
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch_ros.actions import Node
    description = launch_file.generate_launch_description()
    arguments = {e.name for e in description.entities if isinstance(e, DeclareLaunchArgument)}
    assert arguments == ARGUMENTS
    launch_context = launch.LaunchContext()
    context.update(robots='robot1 robot2', sim='true')
    launch_context.launch_configurations.update(context)
    team, = [e for e in description.entities if isinstance(e, OpaqueFunction)]
    nodes = team.execute(launch_context)
    assert all(isinstance(n, Node) for n in nodes)
    assert [n.node_executable for n in nodes] == \
        ['landmark_observer'] * 2 + ['landmark_fuser', 'landmark_sim']
    assert {n.node_package for n in nodes} == {'landmark_ros'}
