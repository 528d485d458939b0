"""The QoS profiles of the package, defined once."""

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, qos_profile_sensor_data, QoSPolicyKind,
                       QoSProfile, ReliabilityPolicy)
from rclpy.qos_overriding_options import QoSOverridingOptions

DIAGNOSTICS = 10
"""Depth of the /diagnostics publishers (default reliable, volatile QoS)."""

LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""QoS of the map outputs and the ground truth: a late subscriber gets the latest."""


def sensor_input(depth):
    """Return the sensor-data QoS profile (best effort, volatile) with the given depth."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=qos_profile_sensor_data.reliability,
                      durability=qos_profile_sensor_data.durability)


def reliable_output(depth):
    """Return a reliable, volatile QoS profile with the given depth."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE)


def replayable_output(depth):
    """
    Return a reliable, transient-local profile: a late subscriber may get the last ``depth``.

    For streams that start as soon as a first subscriber is seen (the simulator): a
    subscriber that matches the writer a moment later and asks for transient local
    (``input_overrides``) still gets what was sent meanwhile; volatile ones match too.
    """
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


def input_overrides():
    """
    Return the QoS overrides an input subscription accepts from parameters.

    ``qos_overrides.<topic>.subscription.{history,depth,reliability,durability}``: the
    ROS 2 defaults and durability (transient local, to get what a ``replayable_output``
    publisher sent before the match).
    """
    return QoSOverridingOptions(policy_kinds=(
        QoSPolicyKind.HISTORY, QoSPolicyKind.DEPTH, QoSPolicyKind.RELIABILITY,
        QoSPolicyKind.DURABILITY))


def replayed_input_overrides(ns, topics):
    """
    Return the parameters that make the inputs ``ns/topic`` reliable and transient local.

    ``{'qos_overrides.<ns>/<topic>.subscription.reliability': 'reliable', ...}``, for
    the subscriptions to a ``replayable_output`` stream that may start before they match.
    """
    return {f'qos_overrides.{ns}/{topic}.subscription.{policy}': value
            for topic in topics
            for policy, value in (('reliability', 'reliable'), ('durability', 'transient_local'))}


def replayed_input_arguments(ns, topics):
    """Return ``replayed_input_overrides`` as node arguments (``-p name:=value`` pairs)."""
    return [arg for name, value in replayed_input_overrides(ns, topics).items()
            for arg in ('-p', f'{name}:={value}')]


def reliable_input(depth):
    """Return the QoS of reliable inputs (the fuser's landmark topics)."""
    return reliable_output(depth)


def incompatible_policy(requested, offered):
    """
    Return the first policy by which a publisher's QoS cannot serve a subscription's.

    DDS matches a writer to a reader only when what the writer offers is at least what
    the reader requests (request vs offered, "RxO", DDS 1.4 section 2.2.3): reliability
    (a best-effort writer and a reliable reader), durability (a volatile writer and a
    transient-local reader) and the deadline (a writer's longer than the reader's).

    Parameters
    ----------
    requested, offered : rclpy.qos.QoSProfile
        The subscription's profile and the publisher's
        (``Node.get_publishers_info_by_topic``).

    Returns
    -------
    str or None
        ``'RELIABILITY'``, ``'DURABILITY'`` or ``'DEADLINE'``; None when they match.

    """
    if (requested.reliability == ReliabilityPolicy.RELIABLE
            and offered.reliability == ReliabilityPolicy.BEST_EFFORT):
        return 'RELIABILITY'
    if (requested.durability == DurabilityPolicy.TRANSIENT_LOCAL
            and offered.durability == DurabilityPolicy.VOLATILE):
        return 'DURABILITY'
    infinite = (0, 0x7fffffffffffffff)
    wanted, given = requested.deadline.nanoseconds, offered.deadline.nanoseconds
    if wanted not in infinite and (given in infinite or given > wanted):
        return 'DEADLINE'
    return None
