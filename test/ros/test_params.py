"""Parameters have exact ROS types; integers written for doubles become doubles."""

from dataclasses import fields

from landmark_ros.nodes.fuser import LandmarkFuser
from landmark_ros.nodes.observer import LandmarkObserver
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.ros.params import parameter_help, parameter_type
from landmark_ros.sim.simulation import SimConfig
import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
import yaml


def test_every_field_has_the_type_of_its_default():
    types = {spec.name: parameter_type(spec) for spec in fields(ObserverConfig)}
    assert types['range_stddev'] == Parameter.Type.DOUBLE
    assert types['max_pending'] == Parameter.Type.INTEGER
    assert types['world_frame'] == Parameter.Type.STRING
    assert types['sensor_pose'] == Parameter.Type.DOUBLE_ARRAY
    assert parameter_type(next(s for s in fields(FuserConfig) if s.name == 'input_topics')) \
        == Parameter.Type.STRING_ARRAY


def test_descriptors_report_exact_types_without_dynamic_typing(env):
    node = env.add(LandmarkObserver(context=env.context))
    names = [spec.name for spec in fields(ObserverConfig)]
    for spec, described in zip(fields(ObserverConfig), node.describe_parameters(names)):
        assert described.type == parameter_type(spec).value, spec.name
        assert not described.dynamic_typing, spec.name
        assert node.get_parameter_types([spec.name])[0] == described.type
    described, = node.describe_parameters(['range_stddev'])
    assert described.type == ParameterType.PARAMETER_DOUBLE
    assert described.floating_point_range[0].to_value == 1000.0


def test_an_integer_set_on_a_double_is_coerced_and_stays_a_double(env):
    node = env.add(LandmarkObserver(context=env.context))
    result, = node.set_parameters([Parameter('range_stddev', value=1)])
    assert result.successful, result.reason
    value = node.get_parameter('range_stddev')
    assert value.type_ == Parameter.Type.DOUBLE and value.value == 1.0
    assert node.config.range_stddev == 1.0 and type(node.config.range_stddev) is float
    assert node.describe_parameters(['range_stddev'])[0].type == ParameterType.PARAMETER_DOUBLE
    # Other types are still refused, and an integer out of range too.
    for parameter in (Parameter('range_stddev', value='wide'),
                      Parameter('range_stddev', value=True),
                      Parameter('range_stddev', value=-1),
                      Parameter('max_pending', value=2.0),
                      Parameter('marker_sigma', value=[1.0])):
        result, = node.set_parameters([parameter])
        assert not result.successful, parameter
        assert result.reason
    assert node.get_parameter('range_stddev').value == 1.0
    assert node.get_parameter('range_stddev').type_ == Parameter.Type.DOUBLE


def test_command_line_integers_for_doubles_and_double_arrays(ros_env):
    env = ros_env(args=['--ros-args', '-p', 'range_stddev:=1', '-p', 'sensor_pose:=[0, 0, 1]',
                        '-p', 'max_wait_s:=2'])
    node = env.add(LandmarkObserver(context=env.context))
    stddev, pose = node.get_parameters(['range_stddev', 'sensor_pose'])
    assert stddev.type_ == Parameter.Type.DOUBLE and stddev.value == 1.0
    assert pose.type_ == Parameter.Type.DOUBLE_ARRAY and list(pose.value) == [0.0, 0.0, 1.0]
    assert node.config.sensor_pose == (0.0, 0.0, 1.0)
    assert node.config.max_wait_s == 2.0


def test_params_file_with_integers_for_doubles_loads(ros_env, tmp_path):
    path = tmp_path / 'observer.yaml'
    path.write_text(yaml.safe_dump({'/**/landmark_observer': {'ros__parameters': {
        'range_stddev': 1, 'bearing_stddev': 0, 'sensor_pose': [1, 0, 0],
        'marker_rate_hz': 10, 'max_pending': 7}}}))
    env = ros_env(args=['--ros-args', '--params-file', str(path), '-r', '__ns:=/robot9'])
    node = env.add(LandmarkObserver(context=env.context))
    assert node.get_parameter('range_stddev').type_ == Parameter.Type.DOUBLE
    assert node.get_parameter('sensor_pose').type_ == Parameter.Type.DOUBLE_ARRAY
    assert node.get_parameter('max_pending').type_ == Parameter.Type.INTEGER
    config = node.config
    assert (config.range_stddev, config.bearing_stddev, config.marker_rate_hz) == (1.0, 0.0, 10.0)
    assert config.sensor_pose == (1.0, 0.0, 0.0) and config.max_pending == 7


def test_parameter_overrides_with_integers_for_doubles(env):
    node = env.add(LandmarkObserver(context=env.context, parameter_overrides=[
        Parameter('range_stddev', value=2), Parameter('sensor_pose', value=[1, 2, 3])]))
    assert node.get_parameter('range_stddev').type_ == Parameter.Type.DOUBLE
    assert node.config.sensor_pose == (1.0, 2.0, 3.0)


@pytest.mark.parametrize('override, message', [
    ('range_stddev:=wide', 'range_stddev is of type double, got the string'),
    ('max_pending:=2.5', 'max_pending is of type integer'),
    ('world_frame:=3', "write e.g. world_frame:='map'"),
    ('sensor_pose:=[0, 1]', 'sensor_pose must have 3 entries'),
    ('sensor_pose:=[]', 'sensor_pose must have 3 entries'),
])
def test_wrong_command_line_types_say_what_to_write(ros_env, override, message):
    env = ros_env(args=['--ros-args', '-p', override])
    with pytest.raises(ValueError, match=message.replace('[', r'\[')):
        LandmarkObserver(context=env.context)


def test_an_empty_topic_list_gives_the_packages_own_message(ros_env):
    env = ros_env(args=['--ros-args', '-p', 'input_topics:=[]'])
    with pytest.raises(ValueError, match='input_topics must list at least one topic name'):
        LandmarkFuser(context=env.context)


@pytest.mark.parametrize('config_class', [ObserverConfig, FuserConfig, SimConfig])
def test_help_lists_every_parameter_with_type_and_default(config_class):
    text = parameter_help(config_class)
    for spec in fields(config_class):
        assert f'\n  {spec.name} (' in '\n' + text, spec.name
    assert all(len(line) <= 79 for line in text.splitlines() if line.startswith('      '))
    if config_class is ObserverConfig:
        assert '  range_stddev (double, default 0.1, 0 to 1000)' in text
        assert '  sensor_pose (double[], default [0.0, 0.0, 0.0], read-only)' in text


def test_ros2_param_set_with_an_integer_over_the_service(env):
    # What `ros2 param set /landmark_observer range_stddev 1` sends.
    node = env.add(LandmarkObserver(context=env.context))
    client = AsyncParameterClient(env.node('param_client'), 'landmark_observer')
    assert env.spin_until(lambda: client.services_are_ready(), 10.0)
    future = client.set_parameters([Parameter('range_stddev', value=1)])
    assert env.spin_until(future.done, 10.0)
    result, = future.result().results
    assert result.successful, result.reason
    future = client.describe_parameters(['range_stddev'])
    assert env.spin_until(future.done, 10.0)
    assert future.result().descriptors[0].type == ParameterType.PARAMETER_DOUBLE
    assert node.get_parameter('range_stddev').value == 1.0
    assert node.config.range_stddev == 1.0
