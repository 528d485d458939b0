"""RViz markers for landmark estimates: k-sigma ellipses and ID labels."""

from builtin_interfaces.msg import Duration
from landmark_ros.core.ellipse import ellipse_axes
import numpy as np
from visualization_msgs.msg import Marker, MarkerArray


ELLIPSE_HEIGHT = 0.02
"""Thickness of the flat cylinder that draws an ellipse [m]."""


def marker_id(landmark_id):
    """
    Return the int32 ``Marker.id`` of a landmark ID in 0..2^32-1 (two's complement).

    IDs above 2^31 - 1 wrap to negative markers IDs, one to one.
    """
    return landmark_id - (1 << 32) if landmark_id >= 1 << 31 else landmark_id


def landmark_markers(header, ids, m, P_m, sigma, lifetime_s=0.0, rgb=(0.1, 0.6, 1.0),
                     prefix=''):
    """
    Return one ellipse and one text label per landmark.

    Markers are keyed by landmark ID (namespaces ``<prefix>ellipses`` and
    ``<prefix>labels``; ``marker_id``), so a newer estimate replaces the older one in
    RViz.

    Parameters
    ----------
    header : std_msgs.msg.Header
        Stamp and frame of the message.
    ids : sequence of int, length N
        Landmark IDs.
    m : ndarray, shape (N, 2) [m]
        Landmark position in the world.
    P_m : ndarray, shape (N, 2, 2) [m^2]
        Covariance of the landmark.
    sigma : float
        Ellipse size in standard deviations.
    lifetime_s : float
        0 keeps the markers until replaced or deleted.
    rgb : tuple of float
        Colour of the ellipses, each channel in [0, 1].
    prefix : str
        Prefix of the marker namespaces.

    Returns
    -------
    visualization_msgs.msg.MarkerArray

    """
    major, minor, angle = (np.atleast_1d(v) for v in ellipse_axes(P_m, sigma))
    lifetime = Duration(sec=int(lifetime_s), nanosec=int((lifetime_s % 1.0) * 1e9))
    markers = []
    for i, landmark_id in enumerate(int(v) for v in ids):
        ellipse = Marker(header=header, ns=prefix + 'ellipses', id=marker_id(landmark_id),
                         type=Marker.CYLINDER, action=Marker.ADD, lifetime=lifetime)
        ellipse.pose.position.x, ellipse.pose.position.y = float(m[i, 0]), float(m[i, 1])
        ellipse.pose.orientation.z = float(np.sin(angle[i] / 2.0))
        ellipse.pose.orientation.w = float(np.cos(angle[i] / 2.0))
        ellipse.scale.x = max(2.0 * float(major[i]), 1e-3)
        ellipse.scale.y = max(2.0 * float(minor[i]), 1e-3)
        ellipse.scale.z = ELLIPSE_HEIGHT
        ellipse.color.r, ellipse.color.g, ellipse.color.b, ellipse.color.a = (*rgb, 0.5)
        label = Marker(header=header, ns=prefix + 'labels', id=marker_id(landmark_id),
                       type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, lifetime=lifetime,
                       text=str(landmark_id))
        label.pose.position.x, label.pose.position.y = float(m[i, 0]), float(m[i, 1])
        label.pose.position.z = 0.3
        label.pose.orientation.w = 1.0
        label.scale.z = 0.25
        label.color.r = label.color.g = label.color.b = label.color.a = 1.0
        markers += [ellipse, label]
    return MarkerArray(markers=markers)


def delete_markers(header, ids, prefix=''):
    """Return a MarkerArray that deletes the ellipse and label of each landmark ID."""
    return MarkerArray(markers=[
        Marker(header=header, ns=prefix + ns, id=marker_id(int(landmark_id)),
               action=Marker.DELETE)
        for landmark_id in ids for ns in ('ellipses', 'labels')])


def delete_all(header):
    """Return a MarkerArray that clears every marker of the topic."""
    return MarkerArray(markers=[Marker(header=header, action=Marker.DELETEALL)])
