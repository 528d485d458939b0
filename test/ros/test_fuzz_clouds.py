"""
Property-based fuzz of every cloud reader: malformed input gives a named reason, nothing else.

Every ``PointCloud2`` the strategy builds (random fields, offsets, datatypes, counts,
steps, sizes, byte order and bytes) is read by each reader the nodes use, raw and
through ``cloud_bytes.read_cloud_bytes``; what reads is then handed to the pipeline
object the node hands it to. The property: a reader returns or raises ``CloudError``
with a reason; the pipeline call returns; no other exception (which a node would
count as ``internal_error``) ever comes out.

``make test`` runs ``FUZZ_EXAMPLES`` (default 150) derandomized examples per test;
``make fuzz`` runs many more (``LANDMARK_FUZZ_EXAMPLES``) with a random seed.
"""

import os

from hypothesis import given, HealthCheck, settings, strategies as st
from landmark_ros.fuser.fuser import Fuser
from landmark_ros.fuser.sources import LandmarkMessage
from landmark_ros.observer.observer import ObservationMessage, Observer
from landmark_ros.pipeline.config import FuserConfig, ObserverConfig
from landmark_ros.ros.cloud import CloudError, read_columns
from landmark_ros.ros.cloud_bytes import read_cloud_bytes
from landmark_ros.ros.schemas import (LANDMARK_SCHEMA, OBSERVATION_FIELDS, PARTIAL_SCHEMA,
                                      read_landmark_cloud, read_landmark_clouds,
                                      read_partial_observations, read_removed, SCAN_FIELDS)
import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import PointCloud2, PointField

EXAMPLES = int(os.environ.get('LANDMARK_FUZZ_EXAMPLES', '150'))
RANDOM = os.environ.get('LANDMARK_FUZZ_RANDOM', '') == '1'
FUZZ = settings(max_examples=EXAMPLES, deadline=None, derandomize=not RANDOM,
                database=None, suppress_health_check=list(HealthCheck))

NAMES = sorted({name for name, _ in LANDMARK_SCHEMA} | {s.name for s in OBSERVATION_FIELDS}
               | {name for name, _ in PARTIAL_SCHEMA} | set(SCAN_FIELDS)
               | {'merged_into', 'observations', 'junk'})


@st.composite
def clouds(draw):
    """Return a PointCloud2 with an arbitrary layout, mostly near-consistent sizes."""
    fields = draw(st.lists(st.builds(
        PointField, name=st.sampled_from(NAMES), offset=st.integers(0, 80),
        datatype=st.integers(0, 9), count=st.integers(0, 2)), max_size=12))
    msg = PointCloud2(fields=fields)
    msg.is_bigendian = draw(st.booleans())
    msg.point_step = draw(st.one_of(st.integers(0, 96), st.integers(0, 2 ** 32 - 1)))
    msg.width = draw(st.integers(0, 6))
    msg.height = draw(st.integers(0, 3))
    exact = msg.width * msg.point_step
    msg.row_step = draw(st.one_of(st.just(exact), st.integers(0, 600),
                                  st.integers(0, 2 ** 32 - 1))) if exact < 4096 else draw(
        st.integers(0, 2 ** 32 - 1))
    size = msg.row_step * msg.height
    length = draw(st.one_of(st.just(size), st.integers(0, 700))) if size < 4096 else draw(
        st.integers(0, 700))
    msg.data = draw(st.binary(min_size=length, max_size=length))
    msg.header.stamp.sec = draw(st.integers(0, 5))
    msg.header.frame_id = draw(st.sampled_from(['map', 'sensor', '']))
    return msg


def _both(msg):
    """Return the message and what ``read_cloud_bytes`` makes of its bytes."""
    return [msg, read_cloud_bytes(serialize_message(msg))]


def _observer():
    observer = Observer(ObserverConfig(max_wait_s=0.0))
    for stamp in (1, 6 * 10 ** 9):
        observer.add_pose(stamp, np.zeros(3), np.eye(3) * 0.01)
    return observer


@FUZZ
@given(clouds())
def test_observation_clouds_give_a_reason_or_landmarks(msg):
    for cloud in _both(msg):
        observer = _observer()
        try:
            columns = read_columns(cloud, OBSERVATION_FIELDS)
        except CloudError as error:
            assert error.reason
            continue
        stamp = cloud.header.stamp.sec * 10 ** 9 + 1
        observer.add_observations([ObservationMessage(stamp, columns, None)])
        assert 'internal_error' not in observer.counters.counts


def _fuser():
    return Fuser(FuserConfig(input_topics=('a',)), ('a',))


@FUZZ
@given(st.lists(clouds(), min_size=1, max_size=3))
def test_landmark_clouds_give_a_reason_or_rows(msgs):
    fuser = _fuser()
    clouds_read = [cloud for msg in msgs for cloud in _both(msg)]
    for cloud, read in zip(clouds_read, read_landmark_clouds(clouds_read)):
        try:
            alone = read_landmark_cloud(cloud)
        except CloudError as error:
            assert isinstance(read, CloudError) and read.reason == error.reason
            continue
        rows, extras = read
        np.testing.assert_array_equal(rows.ids, alone[0].ids)
        fuser.add_landmarks('a', LandmarkMessage(1 + cloud.header.stamp.sec * 10 ** 9, rows.ids,
                                                 rows.m, rows.P, rows.P_dep, 'map',
                                                 extras.classes, extras.scan), 0)
    fuser.fuse_queued()
    fuser.statuses(0)


@FUZZ
@given(clouds())
def test_partial_observation_and_removal_clouds_give_a_reason_or_rows(msg):
    fuser = _fuser()
    for cloud in _both(msg):
        try:
            read_removed(cloud)
        except CloudError as error:
            assert error.reason
        try:
            columns = read_partial_observations(cloud)
        except CloudError as error:
            assert error.reason
            continue
        fuser.add_partial_observations('a', 1 + cloud.header.stamp.sec * 10 ** 9, columns,
                                       'map', 0)
    fuser.fuse_queued()


@FUZZ
@given(st.binary(max_size=300))
def test_serialized_bytes_give_a_cloud_or_malformed_message(raw):
    try:
        cloud = read_cloud_bytes(raw)
    except CloudError as error:
        assert error.reason == 'malformed_message'
        return
    try:
        read_columns(cloud, OBSERVATION_FIELDS)
    except CloudError as error:
        assert error.reason


@pytest.mark.parametrize('change, reason', [
    ({}, 'missing_field'),
    ({'width': 3, 'height': 1, 'point_step': 0, 'row_step': 0}, 'point_step_invalid'),
])
def test_the_issue_examples_are_named_reasons(change, reason):
    msg = PointCloud2()
    for name, value in change.items():
        setattr(msg, name, value)
    observer = _observer()
    try:
        columns = read_columns(msg, OBSERVATION_FIELDS)
    except CloudError as error:
        observer.reject(error.reason)
    else:
        observer.add_observations([ObservationMessage(10 ** 9, columns, None)])
    assert observer.counters[reason] == 1
