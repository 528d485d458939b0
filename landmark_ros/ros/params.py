"""Declare a config dataclass as ROS parameters and keep it in sync at run time."""

from dataclasses import fields, replace

from landmark_ros.pipeline.config import field_default
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)


def descriptor(spec):
    """Return the ParameterDescriptor of one config field."""
    meta = spec.metadata
    default = field_default(spec)
    result = ParameterDescriptor(description=meta['description'], read_only=meta['read_only'])
    low, high = meta['low'], meta['high']
    if isinstance(default, float):
        # Integers in a YAML file are accepted for doubles; the dataclass converts them.
        result.dynamic_typing = True
        if low is not None and high is not None:
            result.floating_point_range = [
                FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
    elif isinstance(default, int) and not isinstance(default, bool):
        if low is not None and high is not None:
            result.integer_range = [
                IntegerRange(from_value=int(low), to_value=int(high), step=1)]
    return result


def _ros_value(spec):
    default = field_default(spec)
    return list(default) if isinstance(default, tuple) else default


def declare_config(node, config_class):
    """
    Declare every field of ``config_class`` on ``node`` and return the config.

    Raises
    ------
    ValueError
        If the values given to the node (parameter file, overrides) are invalid.

    """
    node.declare_parameters('', [
        (spec.name, _ros_value(spec), descriptor(spec)) for spec in fields(config_class)])
    return config_class.from_values(
        {spec.name: node.get_parameter(spec.name).value for spec in fields(config_class)})


def keep_in_sync(node, get_config, set_config):
    """
    Validate parameter changes through the config and apply them when valid.

    Parameters
    ----------
    node : rclpy.node.Node
        The node whose parameters to watch.
    get_config : callable
        Returns the current config.
    set_config : callable
        Receives the new config after a successful change.

    """
    def on_set(parameters):
        names = {spec.name for spec in fields(get_config())}
        changes = {p.name: p.value for p in parameters if p.name in names}
        if not changes:
            return SetParametersResult(successful=True)
        try:
            config = replace(get_config(), **changes)
        except (TypeError, ValueError) as error:
            return SetParametersResult(successful=False, reason=str(error))
        set_config(config)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(on_set)
