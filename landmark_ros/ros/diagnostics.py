"""Diagnostics messages: the pipeline's ``Status`` records as ``DiagnosticArray``."""

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from landmark_ros.pipeline.counters import status_values

LEVELS = {'ok': DiagnosticStatus.OK, 'warn': DiagnosticStatus.WARN,
          'error': DiagnosticStatus.ERROR}


def status(level, name, message, hardware_id, counts, extra=None):
    """
    Return a DiagnosticStatus with the counters (and extra values) as key-values.

    Parameters
    ----------
    level : bytes
        ``DiagnosticStatus.OK``, ``WARN``, ...
    name : str
        Status name (the node's fully qualified name, or more).
    message : str
        One line of summary.
    hardware_id : str
        What the status is about.
    counts : dict
        Counters.
    extra : dict, optional
        More values, shown first.

    """
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=v)
                                    for k, v in status_values(counts, extra)])


def to_msg(record, node_name, hardware_id):
    """
    Return the DiagnosticStatus of a pipeline ``Status``.

    Parameters
    ----------
    record : landmark_ros.pipeline.counters.Status
        The status; ``record.name`` (when set) is appended to the node name and is
        the hardware ID.
    node_name : str
        The node's fully qualified name.
    hardware_id : str
        Hardware ID of a status without a name (the node's namespace).

    """
    name = f'{node_name}: {record.name}' if record.name else node_name
    return status(LEVELS[record.level], name, record.message, record.name or hardware_id,
                  record.counts, record.extra)


def publish(node, publisher, statuses):
    """Publish statuses as one DiagnosticArray stamped with the node's clock."""
    array = DiagnosticArray(status=list(statuses))
    array.header.stamp = node.get_clock().now().to_msg()
    publisher.publish(array)
