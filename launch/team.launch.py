"""
Launch a landmark_ros team: one landmark_observer per robot and one landmark_fuser.

    ros2 launch landmark_ros team.launch.py sim:=true      # the whole simulated demo
    ros2 launch landmark_ros team.launch.py robots:='alpha beta' \
        observer_params:=/path/observer.yaml fuser_params:=/path/fuser.yaml \
        fusion:=covariance_intersection rviz:=true

Each observer runs in its robot's namespace (``/<robot>/landmark_observer``: ``pose``
or ``odometry`` and ``observations`` in, ``landmarks`` and the partial observations
out) with ``observer_params``. The fuser reads ``fuser_params`` and fuses the outputs
of every robot named in ``robots``: its per-robot topic parameters (``FUSER_INPUTS``)
follow ``robots``, whatever the file says (with the observers' ``precision_sources``
from ``observer_params``, each robot's ``landmarks/precision_k`` topics too). The
parameter files key on the node names
``landmark_observer``, ``landmark_fuser`` and ``landmark_sim``, as the shipped ones do.

``sim:=true`` also starts ``landmark_sim`` with ``sim_params`` and as many robots as
``robots`` names, its ``robot<i>/...`` topics remapped to the names given. ``fusion``
('' keeps the file's value) sets the fuser's fusion method.

``localize:=true`` is the team without motion capture: one ``landmark_localizer`` per
robot (``/<robot>/landmark_localizer``, ``localizer_params`` if given) takes the
robot's ``odometry`` and ``observations`` and the fuser's ``/fused_landmarks``, and
publishes ``/<robot>/pose``, the pose the observer takes: the observers place the
sightings with the localizers' poses, the fuser builds the map, the localizers use it
(``localizer_overrides``); the fuser's change detection is off in the loop (its rows
carry the localizers' slow pose errors). With ``sim:=true`` the simulator's own ``pose`` goes to
``/<robot>/sim_pose`` (unused), the localizers run on its wheel odometry and start at
the simulated robots' true starting poses, with the simulator's noise models.

Everything is checked before any process starts (``check_team``): the robot names, that
each parameter file exists and parses as YAML, the fusion method, and with
``rviz:=true`` that rviz2 is installed. A failed check ends the launch with one line
(exit code 1) and no process started. A team process that exits with an error once
started shuts the whole launch down, so no part of the team is left running alone.
"""

from importlib import import_module
import os
import re

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare
import yaml

PACKAGE = 'landmark_ros'

FUSER_INPUTS = {
    'input_topics': 'landmarks',
    'partial_observation_topics': 'partial_observations',
}
"""Fuser parameter -> the topic, relative to each robot's namespace, that it lists per
robot: the one place that names the per-robot topics the fuser subscribes."""

SIM_TOPICS = ('pose', 'true_pose', 'observations', 'odometry')
"""The per-robot topics of landmark_sim, remapped to the robot names given."""
SIM_WAIT_S = 60.0
"""With ``localize:=true`` the simulator waits up to this long [wall s] for every
subscriber, the localizers' odometry included (not its own pose, which nobody takes
then), before its first step."""

STOP_TIMEOUT_S = '20'
"""Seconds a team process has between Ctrl-C (SIGINT) and SIGTERM: a node that loaded
numba spends one to a few seconds unloading it at exit on a busy machine, more than
launch's default of 5 s."""

FUSION_MODULES = ('landmark_ros.fusion', 'landmark_ros.fusion.landmark_map',
                  'landmark_ros.core.landmark_map')
"""Where ``FUSION_METHODS`` may be found (the first that has it is used)."""


class TeamError(RuntimeError):
    """A launch argument that cannot start the team; the message is one line."""


def robot_names(text):
    """
    Return the robot names (namespaces) of the ``robots`` argument.

    Parameters
    ----------
    text : str
        Names separated by spaces or commas; leading and trailing '/' are dropped.

    Returns
    -------
    list of str

    Raises
    ------
    ValueError
        If there is no name or a name repeats.

    """
    names = [name.strip('/') for name in re.split(r'[\s,]+', text) if name.strip('/')]
    if not names:
        raise ValueError('robots: give at least one robot name')
    if len(set(names)) != len(names):
        raise ValueError(f'robots: {text!r} names a robot twice')
    return names


def fuser_topics(robots, precision_sources=1):
    """
    Return the fuser's per-robot topic parameters for ``robots``.

    Parameters
    ----------
    robots : list of str
        Robot names.
    precision_sources : int
        The observers' ``precision_sources``: each robot's landmark topics
        (``landmarks`` and ``landmarks/precision_k``, ``observer.precision``).

    Returns
    -------
    dict of str to list of str
        ``FUSER_INPUTS`` parameter -> ``/<robot>/<topic>`` for each robot, in order.

    """
    from landmark_ros.observer.precision import precision_topics
    out = {parameter: [f'/{robot}/{topic}' for robot in robots]
           for parameter, topic in FUSER_INPUTS.items()}
    out['input_topics'] = [topic for robot_topic in out['input_topics']
                           for topic in precision_topics(robot_topic, precision_sources)]
    return out


def node_section(path, node):
    """Return the ``ros__parameters`` of ``node`` in the parameter file ``path`` (merged)."""
    with open(path, encoding='utf-8') as stream:
        document = yaml.safe_load(stream) or {}
    values = {}
    for key, section in document.items():
        if str(key).rstrip('/').split('/')[-1] == node:
            values.update((section or {}).get('ros__parameters') or {})
    return values


def precision_sources_of(path):
    """Return the observers' ``precision_sources`` in ``path``; TeamError if not 1 to 16."""
    value = node_section(path, 'landmark_observer').get('precision_sources', 1)
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 16:
        raise TeamError(f'observer_params: precision_sources must be an integer from 1 to '
                        f'16, got {value!r} in {path}')
    return value


def sim_remappings(robots, localize=False):
    """
    Return the remappings of landmark_sim's ``robot<i>/<topic>`` to the names given.

    With ``localize`` the simulator's reported ``pose`` goes to ``/<robot>/sim_pose``:
    the localizers publish ``/<robot>/pose``.
    """
    out = []
    for i, robot in enumerate(robots, start=1):
        for topic in SIM_TOPICS:
            target = 'sim_pose' if localize and topic == 'pose' else topic
            if f'robot{i}/{topic}' != f'{robot}/{target}':
                out.append((f'robot{i}/{topic}', f'/{robot}/{target}'))
    return out


def localizer_overrides(robots, sim_params=None):
    """
    Return per robot the parameters the launch gives its ``landmark_localizer``.

    The other robots are ``other_robots``; with ``sim_params`` (``sim:=true``) the
    simulator's odometry and sensor noise and the robot's true starting pose
    (``landmark_ros.sim.simulation.Simulation``, from the same parameters) with a
    small covariance.
    """
    out = [{'other_robots': [other for other in robots if other != robot] or ['']}
           for robot in robots]
    if sim_params is None:
        return out
    from landmark_ros.sim.simulation import SimConfig, Simulation
    values = node_section(sim_params, 'landmark_sim')
    values['robots'] = len(robots)
    sim = Simulation(SimConfig.from_values(values))
    config = sim.config
    for i, overrides in enumerate(out):
        overrides.update({
            'odometry_alphas': [float(a) for a in config.odometry_alphas],
            'range_stddev': float(config.range_stddev), 'range_stddev_per_m': 0.0,
            'bearing_stddev': float(config.bearing_stddev),
            'initial_pose': [float(v) for v in sim.true_pose(i, 0.0)],
            'initial_stddev': [0.05, 0.05, 0.02]})
    return out


def fusion_methods():
    """Return the fusion method names the package knows (None when none is found)."""
    for name in FUSION_MODULES:
        try:
            return tuple(import_module(name).FUSION_METHODS)
        except (ImportError, AttributeError):
            continue
    return None


def check_params_file(argument, path):
    """Raise TeamError unless ``path`` is a readable YAML parameter file."""
    if not os.path.isfile(path):
        raise TeamError(f'{argument}: no such parameter file: {path}')
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        problem = ' '.join(str(error).split())
        raise TeamError(f'{argument}: cannot read {path}: {problem}') from None
    if not isinstance(document, dict):
        raise TeamError(f'{argument}: {path} is no ROS parameter file (not a mapping)')


def rviz_installed():
    """Return whether the rviz2 package and its executable are installed."""
    try:
        from ament_index_python.packages import get_package_prefix, PackageNotFoundError
    except ImportError:
        return False
    try:
        prefix = get_package_prefix('rviz2')
    except (PackageNotFoundError, ValueError, OSError):   # OSError: no AMENT_PREFIX_PATH
        return False
    return os.access(os.path.join(prefix, 'lib', 'rviz2', 'rviz2'), os.X_OK)


def check_team(arguments):
    """
    Check the launch arguments before anything starts; return the robot names.

    Parameters
    ----------
    arguments : dict of str to str
        The launch arguments, performed.

    Returns
    -------
    list of str

    Raises
    ------
    TeamError
        With one line naming the argument: no robot or a repeated one, a parameter
        file that is missing or not YAML, the observers' ``precision_sources`` not an
        integer from 1 to 16, an unknown fusion method, ``sim`` or
        ``rviz`` neither true nor false, or ``rviz:=true`` without rviz2 installed.

    """
    try:
        robots = robot_names(arguments['robots'])
    except ValueError as error:
        raise TeamError(str(error)) from None
    flags = {}
    for name in ('sim', 'rviz', 'localize'):
        text = arguments[name].strip().lower()
        if text not in ('true', 'false'):
            raise TeamError(f'{name}: expected true or false, got {arguments[name]!r}')
        flags[name] = text == 'true'
    files = ['observer_params', 'fuser_params'] + (['sim_params'] if flags['sim'] else [])
    if flags['localize'] and arguments['localizer_params']:
        files.append('localizer_params')
    for name in files:
        check_params_file(name, arguments[name])
    precision_sources_of(arguments['observer_params'])
    methods = fusion_methods()
    if arguments['fusion'] and methods is not None and arguments['fusion'] not in methods:
        raise TeamError(f"fusion: {arguments['fusion']!r} is not one of {', '.join(methods)}")
    if flags['rviz'] and not rviz_installed():
        raise TeamError("rviz: package 'rviz2' is not installed (install ros-jazzy-rviz2, "
                        'or launch without rviz:=true)')
    return robots


def on_failure(event, context):
    """Shut the launch down when a team process exits with an error (not at shutdown)."""
    if event.returncode == 0 or context.is_shutdown:
        return None
    return [Shutdown(reason=f'{event.process_name} exited with code {event.returncode}: '
                            'stopping the team')]


def team_nodes(robots, arguments):
    """
    Return the Node actions of a team: the observers, the fuser, then sim and RViz.

    Parameters
    ----------
    robots : list of str
        Robot names, each the namespace of its observer.
    arguments : dict of str to str
        The launch arguments (``check_team`` accepted them).

    Returns
    -------
    list of launch_ros.actions.Node

    """
    common = {'package': PACKAGE, 'output': 'screen', 'on_exit': on_failure,
              'sigterm_timeout': STOP_TIMEOUT_S}
    sim = arguments['sim'].strip().lower() == 'true'
    localize = arguments['localize'].strip().lower() == 'true'
    from_sim = ('observations',) if localize else ('observations', 'pose')  # else localizers'
    nodes = [Node(executable='landmark_observer', name='landmark_observer', namespace=robot,
                  parameters=[arguments['observer_params'],
                              *replayed_inputs(robot, from_sim, sim)],
                  **common) for robot in robots]
    overrides = fuser_topics(robots, precision_sources_of(arguments['observer_params']))
    if localize:    # the loop's rows carry slow pose errors: no change detection (slam.md)
        overrides['move_false_alarm_rate'] = 0.0
    if arguments['fusion']:
        overrides['fusion'] = arguments['fusion']
    nodes.append(Node(executable='landmark_fuser', name='landmark_fuser',
                      parameters=[arguments['fuser_params'], overrides], **common))
    if localize:
        nodes += localizer_nodes(robots, arguments, sim, common)
    if sim:
        sim_overrides = {'robots': len(robots)}
        if localize:  # the localizers start at the first pose: they need the first odometry
            sim_overrides.update(wait_for_odometry_subscribers=True,
                                 wait_for_pose_subscribers=False,   # sim_pose: unused
                                 wait_for_subscribers_s=SIM_WAIT_S)
        nodes.append(Node(executable='landmark_sim', name='landmark_sim',
                          parameters=[arguments['sim_params'], sim_overrides],
                          remappings=sim_remappings(robots, localize), **common))
    if arguments['rviz'].strip().lower() == 'true':
        nodes.append(Node(package='rviz2', executable='rviz2', name='rviz2',
                          arguments=['-d', arguments['rviz_config']]))
    return nodes


def replayed_inputs(robot, topics, sim):
    """
    Return the QoS overrides of a robot's inputs from the simulator: ``[dict]``, or ``[]``.

    The simulator starts once each stream has one subscriber; with the localizers a
    robot's observations have two, and the one that matches a moment later gets what
    was sent meanwhile only as a reliable, transient-local reader
    (``landmark_ros.ros.qos.replayed_input_overrides``).
    """
    if not sim:
        return []
    from landmark_ros.ros.qos import replayed_input_overrides
    return [replayed_input_overrides(f'/{robot}', topics)]


def localizer_nodes(robots, arguments, sim, common):
    """Return one ``landmark_localizer`` per robot, on the fuser's map (``localize:=true``)."""
    files = [arguments['localizer_params']] if arguments['localizer_params'] else []
    overrides = localizer_overrides(robots, arguments['sim_params'] if sim else None)
    return [Node(executable='landmark_localizer', name='landmark_localizer', namespace=robot,
                 parameters=[*files, extra,
                             *replayed_inputs(robot, ('odometry', 'observations'), sim)],
                 remappings=[('fused_landmarks', '/fused_landmarks')], **common)
            for robot, extra in zip(robots, overrides)]


ARGUMENTS = ('robots', 'observer_params', 'fuser_params', 'sim', 'sim_params', 'fusion',
             'rviz', 'rviz_config', 'localize', 'localizer_params')


def _team(context):
    arguments = {name: LaunchConfiguration(name).perform(context) for name in ARGUMENTS}
    return team_nodes(check_team(arguments), arguments)


def generate_launch_description():
    """Return the team: arguments, then one action that checks them and starts it."""
    share = FindPackageShare(PACKAGE)
    return LaunchDescription([
        DeclareLaunchArgument(
            'robots', default_value='robot1 robot2 robot3',
            description='Robot names, separated by spaces or commas; each is the namespace '
                        'of one landmark_observer, and the fuser subscribes to the outputs '
                        'of each.'),
        DeclareLaunchArgument(
            'observer_params',
            default_value=PathJoinSubstitution([share, 'config', 'observer.yaml']),
            description='Parameter file of every landmark_observer (must exist).'),
        DeclareLaunchArgument(
            'fuser_params',
            default_value=PathJoinSubstitution([share, 'config', 'fuser.yaml']),
            description='Parameter file of the landmark_fuser (must exist; its per-robot '
                        'topics come from robots).'),
        DeclareLaunchArgument(
            'sim', default_value='false',
            description='Also start landmark_sim, simulating the robots named in robots.'),
        DeclareLaunchArgument(
            'sim_params',
            default_value=PathJoinSubstitution([share, 'config', 'sim.yaml']),
            description='Parameter file of landmark_sim with sim:=true (its robots parameter '
                        'comes from robots).'),
        DeclareLaunchArgument(
            'fusion', default_value='',
            description="The fuser's fusion method (independent, covariance_intersection, "
                        "split_covariance_intersection, ...); '' keeps fuser_params' value."),
        DeclareLaunchArgument(
            'localize', default_value='false',
            description='Also start a landmark_localizer per robot: the observers take its '
                        'pose, the localizers the fused map (the team without motion '
                        'capture; with sim:=true on the simulated wheel odometry).'),
        DeclareLaunchArgument(
            'localizer_params', default_value='',
            description='Parameter file of every landmark_localizer with localize:=true '
                        "('' for the defaults)."),
        DeclareLaunchArgument(
            'rviz', default_value='false',
            description='Also start RViz with rviz_config; rviz2 must be installed.'),
        DeclareLaunchArgument(
            'rviz_config',
            default_value=PathJoinSubstitution([share, 'rviz', 'landmarks.rviz']),
            description='RViz configuration (the shipped one shows robot1..robot3).'),
        OpaqueFunction(function=_team),
    ])
