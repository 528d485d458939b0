"""Tests of ros.markers: one ellipse and one label per landmark, keyed by ID."""

from landmark_ros.ros.markers import landmark_markers, marker_id
import numpy as np
from std_msgs.msg import Header


def test_every_landmark_id_has_its_own_int32_marker_id():
    ids = [0, 7, 2 ** 31 - 1, 2 ** 31, 2 ** 32 - 1, 1_000_000_000]
    markers = [marker_id(i) for i in ids]
    assert len(set(markers)) == len(ids)
    assert all(-2 ** 31 <= m < 2 ** 31 for m in markers)
    assert markers[:3] == [0, 7, 2 ** 31 - 1] and markers[4] == -1


def test_markers_of_the_largest_ids_are_built():
    ids = [2 ** 32 - 1, 2 ** 31]
    array = landmark_markers(Header(frame_id='map'), ids, np.zeros((2, 2)),
                             np.broadcast_to(np.eye(2), (2, 2, 2)), 2.0)
    assert [m.id for m in array.markers] == [-1, -1, -2 ** 31, -2 ** 31]
    assert [m.ns for m in array.markers] == ['ellipses', 'labels'] * 2
    assert array.markers[1].text == str(2 ** 32 - 1)
