"""
Declare a config dataclass as ROS parameters and keep it in sync at run time.

Every parameter is declared with its exact type (``ParameterDescriptor.type``, no
dynamic typing), as plain rclpy nodes do: ``describe_parameters`` reports DOUBLE for a
double and a string can never replace it. Integers are still accepted where a double
is declared, the way users write them: ``range_stddev: 1`` in a parameter file,
``-p range_stddev:=1``, ``-p sensor_pose:=[0, 0, 1]`` and ``ros2 param set ...
range_stddev 1`` all give doubles (rclpy itself would refuse them).
"""

from dataclasses import fields, replace
import textwrap

from landmark_ros.pipeline.config import field_default
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.parameter import Parameter

TYPE_NAMES = {
    Parameter.Type.BOOL: 'bool', Parameter.Type.INTEGER: 'integer',
    Parameter.Type.DOUBLE: 'double', Parameter.Type.STRING: 'string',
    Parameter.Type.DOUBLE_ARRAY: 'double[]', Parameter.Type.STRING_ARRAY: 'string[]',
}
"""How the help and the error messages name the parameter types."""

_ARRAY_TYPES = (Parameter.Type.DOUBLE_ARRAY, Parameter.Type.STRING_ARRAY)


def parameter_type(spec):
    """
    Return the ROS type of one config field, from the type of its default.

    Parameters
    ----------
    spec : dataclasses.Field
        A field of a ConfigBase dataclass.

    Returns
    -------
    rclpy.parameter.Parameter.Type
        BOOL, INTEGER, DOUBLE, STRING, DOUBLE_ARRAY or STRING_ARRAY.

    """
    default = field_default(spec)
    if isinstance(default, bool):
        return Parameter.Type.BOOL
    if isinstance(default, int):
        return Parameter.Type.INTEGER
    if isinstance(default, float):
        return Parameter.Type.DOUBLE
    if isinstance(default, str):
        return Parameter.Type.STRING
    if default and isinstance(default[0], str):
        return Parameter.Type.STRING_ARRAY
    return Parameter.Type.DOUBLE_ARRAY


def descriptor(spec):
    """Return the ParameterDescriptor of one config field: exact type, range, read-only."""
    meta = spec.metadata
    kind = parameter_type(spec)
    result = ParameterDescriptor(description=meta['description'], read_only=meta['read_only'],
                                 type=kind.value, dynamic_typing=False)
    low, high = meta['low'], meta['high']
    if low is not None and high is not None:
        if kind == Parameter.Type.DOUBLE:
            result.floating_point_range = [
                FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)]
        elif kind == Parameter.Type.INTEGER:
            result.integer_range = [
                IntegerRange(from_value=int(low), to_value=int(high), step=1)]
    return result


def coerce(parameter, kind):
    """
    Return ``parameter`` with integers turned into doubles where ``kind`` is a double type.

    Parameters
    ----------
    parameter : rclpy.parameter.Parameter
        A value given to the node.
    kind : rclpy.parameter.Parameter.Type or None
        The declared type; None leaves the parameter as it is.

    Returns
    -------
    rclpy.parameter.Parameter
        The same parameter, or a DOUBLE / DOUBLE_ARRAY one with the same numbers.

    """
    given = parameter.type_
    if kind == Parameter.Type.DOUBLE and given == Parameter.Type.INTEGER:
        return Parameter(parameter.name, kind, float(parameter.value))
    if kind == Parameter.Type.DOUBLE_ARRAY and given == Parameter.Type.INTEGER_ARRAY:
        return Parameter(parameter.name, kind, [float(v) for v in parameter.value])
    return parameter


def example(spec):
    """Return how to write the default of a config field after ``-p name:=``."""
    default = field_default(spec)
    if isinstance(default, tuple):
        return '[' + ', '.join(repr(v) for v in default) + ']'
    if isinstance(default, bool):
        return str(default).lower()
    return repr(default) if isinstance(default, (str, float)) else str(default)


def _override(spec, parameter):
    """Return a parameter-file or ``-p`` value the declared type accepts, or raise."""
    kind = parameter_type(spec)
    parameter = coerce(parameter, kind)
    if parameter.type_ != kind:
        got = (f'the {TYPE_NAMES.get(parameter.type_, parameter.type_.name.lower())} '
               f'{parameter.value!r}' if parameter.type_ != Parameter.Type.NOT_SET
               else 'no value')
        raise ValueError(f'{spec.name} is of type {TYPE_NAMES[kind]}, got {got}: write '
                         f'e.g. {spec.name}:={example(spec)}')
    return parameter


def declare_config(node, config_class):
    """
    Declare every field of ``config_class`` on ``node`` and return the config.

    Integers given for doubles (parameter files, ``-p``, ``parameter_overrides``, and
    later ``set_parameters``) are turned into doubles first.

    Raises
    ------
    ValueError
        If the values given to the node (parameter file, overrides) are invalid.

    """
    specs = fields(config_class)
    kinds = {spec.name: parameter_type(spec) for spec in specs}
    # rclpy keeps the parameter-file, -p and parameter_overrides values here and reads
    # them in declare_parameters; they are made to fit the declared types first.
    overrides = node._parameter_overrides
    empty = set()
    for spec in specs:
        if spec.name not in overrides:
            continue
        if (overrides[spec.name].type_ == Parameter.Type.NOT_SET
                and kinds[spec.name] in _ARRAY_TYPES):
            # '[]' reaches rclpy without a type and an empty array cannot be declared
            # with one: the config judges the empty list instead.
            del overrides[spec.name]
            empty.add(spec.name)
        else:
            overrides[spec.name] = _override(spec, overrides[spec.name])
    node.declare_parameters('', [
        (spec.name, _ros_value(spec), descriptor(spec)) for spec in specs])
    node.add_pre_set_parameters_callback(
        lambda parameters: [coerce(p, kinds.get(p.name)) for p in parameters])
    values = {spec.name: node.get_parameter(spec.name).value for spec in specs}
    config = config_class.from_values({**values, **{name: () for name in empty}})
    if empty:
        raise ValueError(f"{', '.join(sorted(empty))}: an empty list cannot be declared")
    return config


def _ros_value(spec):
    default = field_default(spec)
    return list(default) if isinstance(default, tuple) else default


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


def parameter_help(config_class, width=79):
    """
    Return the parameters of a config class as the text of a ``--help``.

    Parameters
    ----------
    config_class : type
        A ConfigBase dataclass.
    width : int
        Line width of the descriptions.

    Returns
    -------
    str
        Per parameter a line ``name (type, default, range, read-only)`` and its
        description, indented.

    """
    lines = []
    for spec in fields(config_class):
        meta = spec.metadata
        facts = [TYPE_NAMES[parameter_type(spec)], f'default {example(spec)}']
        if meta['low'] is not None:
            facts.append(f"{meta['low']:g} to {meta['high']:g}")
        if meta['read_only']:
            facts.append('read-only')
        lines.append(f"  {spec.name} ({', '.join(facts)})")
        lines.extend(textwrap.wrap(meta['description'], width, initial_indent=' ' * 6,
                                   subsequent_indent=' ' * 6))
    return '\n'.join(lines)
