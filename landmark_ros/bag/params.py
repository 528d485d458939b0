"""
Node sections of a ROS 2 parameter file, as a node with that name would read them.

A section applies to a node when its key matches the node's fully qualified name, with
the wildcards of rcl: ``/**`` any number of namespace levels (none included), ``*`` one
name. ``/**:`` applies to every node, ``/**/landmark_observer:`` to every observer,
``/robot1/landmark_observer:`` to the observer of ``robot1`` only; a key without a
leading slash is taken from the root. When several sections set a parameter, the one
later in the file wins.
"""

from pathlib import Path
import re

import yaml


def key_pattern(key):
    """
    Return the regular expression of a parameter-file section key.

    Parameters
    ----------
    key : str
        E.g. ``/**/landmark_observer`` or ``robot1/landmark_observer``.

    Returns
    -------
    re.Pattern
        Matching the fully qualified node names the section applies to.

    """
    parts = []
    for token in str(key).strip('/').split('/'):
        if token == '**':
            parts.append('(?:/[^/]+)*')
        elif token == '*':
            parts.append('/[^/]+')
        else:
            parts.append('/' + re.escape(token).replace(r'\*', '[^/]*'))
    return re.compile(''.join(parts) + r'\Z')


def read_document(path):
    """
    Read a ROS 2 parameter file.

    Parameters
    ----------
    path : str or Path
        The YAML file.

    Returns
    -------
    dict
        Section key -> section.

    Raises
    ------
    ValueError
        If the file cannot be read, is not YAML, or is not a mapping of node sections.

    """
    path = Path(path)
    try:
        with open(path, encoding='utf-8') as stream:
            document = yaml.safe_load(stream)
    except OSError as error:
        raise ValueError(f'cannot read the parameter file {path}: {error.strerror}') from error
    except yaml.YAMLError as error:
        raise ValueError(f'{path}: not valid YAML ({" ".join(str(error).split())})') from error
    document = document or {}
    if not isinstance(document, dict):
        raise ValueError(f'{path}: not a ROS parameter file (a mapping of node sections)')
    return document


def node_parameters(document, node_fqn):
    """
    Return the parameters of the sections that apply to a node, merged in file order.

    Parameters
    ----------
    document : dict
        A parameter file (``read_document``).
    node_fqn : str
        The node's fully qualified name, e.g. ``/robot1/landmark_observer``.

    Returns
    -------
    dict
        Parameter name -> value.

    Raises
    ------
    ValueError
        If a matching section has no ``ros__parameters`` mapping.

    """
    values = {}
    for key, section in (document or {}).items():
        if not key_pattern(key).match(node_fqn):
            continue
        parameters = section.get('ros__parameters') if isinstance(section, dict) else None
        if not isinstance(parameters, dict):
            raise ValueError(f'section {key!r} must hold a ros__parameters mapping')
        values.update(parameters)
    return values


def load_config(config_class, document, node_fqn):
    """
    Build a node's config dataclass from a parameter file.

    Parameters
    ----------
    config_class : type
        ``ObserverConfig`` or ``FuserConfig``.
    document : dict or None
        A parameter file (``read_document``); None gives the defaults.
    node_fqn : str
        The node's fully qualified name.

    Returns
    -------
    config_class instance

    Raises
    ------
    ValueError
        Naming the node, if a value is invalid.

    """
    try:
        return config_class.from_values(node_parameters(document, node_fqn))
    except ValueError as error:
        raise ValueError(f'{node_fqn}: {error}') from error
