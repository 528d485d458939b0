"""
Launch a landmark_ros team: one landmark_observer per robot and one landmark_fuser.

    ros2 launch landmark_ros team.launch.py
    ros2 launch landmark_ros team.launch.py robots:='alpha beta' \
        observer_params:=/path/observer.yaml fuser_params:=/path/fuser.yaml rviz:=true

Each observer runs in its robot's namespace (``/<robot>/landmark_observer``: ``pose``
or ``odometry`` and ``observations`` in, ``landmarks`` out) with ``observer_params``;
the fuser reads ``fuser_params`` and fuses ``/<robot>/landmarks`` of every robot (its
``input_topics`` follow ``robots``, whatever the file says). The parameter files key
on the node names ``landmark_observer`` and ``landmark_fuser``, as the shipped ones do.
"""

import re

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

PACKAGE = 'landmark_ros'


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


def team_nodes(robots, observer_params, fuser_params):
    """
    Return the Node actions of a team: the observers, then the fuser.

    Parameters
    ----------
    robots : list of str
        Robot names, each the namespace of its observer.
    observer_params, fuser_params : str
        Parameter files of the observers and of the fuser.

    Returns
    -------
    list of launch_ros.actions.Node

    """
    observers = [
        Node(package=PACKAGE, executable='landmark_observer', name='landmark_observer',
             namespace=robot, parameters=[observer_params], output='screen')
        for robot in robots]
    fuser = Node(package=PACKAGE, executable='landmark_fuser', name='landmark_fuser',
                 parameters=[fuser_params,
                             {'input_topics': [f'/{robot}/landmarks' for robot in robots]}],
                 output='screen')
    return observers + [fuser]


def _team(context):
    def value(name):
        return LaunchConfiguration(name).perform(context)
    return team_nodes(robot_names(value('robots')), value('observer_params'),
                      value('fuser_params'))


def generate_launch_description():
    """Return the team: arguments, observers and fuser, RViz on request."""
    share = FindPackageShare(PACKAGE)
    return LaunchDescription([
        DeclareLaunchArgument(
            'robots', default_value='robot1 robot2 robot3',
            description='Robot names, separated by spaces or commas; each is the namespace '
                        'of one landmark_observer.'),
        DeclareLaunchArgument(
            'observer_params',
            default_value=PathJoinSubstitution([share, 'config', 'observer.yaml']),
            description='Parameter file of every landmark_observer.'),
        DeclareLaunchArgument(
            'fuser_params',
            default_value=PathJoinSubstitution([share, 'config', 'fuser.yaml']),
            description='Parameter file of the landmark_fuser (input_topics come from '
                        'robots).'),
        DeclareLaunchArgument(
            'rviz', default_value='false',
            description='Also start RViz with rviz/landmarks.rviz (robot1..robot3 markers).'),
        OpaqueFunction(function=_team),
        Node(package='rviz2', executable='rviz2', name='rviz2',
             arguments=['-d', PathJoinSubstitution([share, 'rviz', 'landmarks.rviz'])],
             condition=IfCondition(LaunchConfiguration('rviz'))),
    ])
