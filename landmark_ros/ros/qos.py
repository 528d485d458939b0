"""The QoS profiles of the package, defined once."""

from rclpy.qos import (DurabilityPolicy, HistoryPolicy, qos_profile_sensor_data, QoSProfile,
                       ReliabilityPolicy)

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


def reliable_input(depth):
    """Return the QoS of reliable inputs (the fuser's landmark topics)."""
    return reliable_output(depth)
