"""
Read a serialized ``sensor_msgs/PointCloud2`` without building the Python message.

rclpy's deserialisation makes a Python object per ``PointField`` and copies the data
into an ``array.array``: for a 100-row cloud that is about 60 us of a fuser's
message, more than its row checks. ``read_cloud_bytes`` reads the little-endian CDR
(XCDR1, the encoding Fast DDS and Cyclone DDS send) of the header, the layout and the
fields straight from the bytes, and hands out the data as a ``memoryview`` of them.
The result has the attributes ``cloud.read_columns`` and ``schemas`` read from a
message. Anything else (another encapsulation, or bytes that do not parse to the end)
goes through ``rclpy.serialization.deserialize_message``, so what is accepted, and
how, is what rclpy decides.

Source: the Object Management Group's DDS-XTypes 1.3, section 7.4.3 (CDR encoding,
XCDR version 1): each primitive aligned to its own size from the start of the
payload, after a 4-byte encapsulation header; strings as a uint32 length that counts
the terminating NUL, then the bytes; sequences as a uint32 count, then the elements.
"""

from dataclasses import dataclass
import struct
from typing import Any, Tuple

from landmark_ros.ros.cloud import CloudError
import numpy as np
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2

_LITTLE_ENDIAN_CDR = b'\x00\x01'
"""Encapsulation identifier of little-endian plain CDR (the header's first two bytes)."""

_U32 = struct.Struct('<I')
_STAMP = struct.Struct('<iI')
_TWO_U32 = struct.Struct('<II')


@dataclass(frozen=True)
class Stamp:
    """``builtin_interfaces/Time`` as read: ``sec``, ``nanosec``."""

    sec: int
    nanosec: int


@dataclass(frozen=True)
class Header:
    """``std_msgs/Header`` as read: ``stamp``, ``frame_id``."""

    stamp: Stamp
    frame_id: str


@dataclass(frozen=True)
class Field:
    """``sensor_msgs/PointField`` as read: ``name``, ``offset``, ``datatype``, ``count``."""

    name: str
    offset: int
    datatype: int
    count: int


@dataclass(frozen=True)
class Cloud:
    """The fields of a ``PointCloud2``; ``data`` is a read-only view of the bytes."""

    header: Header
    height: int
    width: int
    fields: Tuple[Field, ...]
    is_bigendian: bool
    point_step: int
    row_step: int
    data: Any
    is_dense: bool
    layout: Tuple[Tuple[str, int, int, int], ...]
    """The fields as ``(name, offset, datatype, count)``: one tuple per layout."""


def read_cloud_bytes(raw):
    """
    Return a serialized ``PointCloud2`` as a ``Cloud`` or, past the fast path, a message.

    Parameters
    ----------
    raw : bytes
        The message as a raw subscription delivers it.

    Returns
    -------
    Cloud or sensor_msgs.msg.PointCloud2
        Either has what ``cloud.read_columns`` and ``schemas.read_landmark_cloud``
        read.

    Raises
    ------
    CloudError
        ``malformed_message`` when rclpy cannot deserialize the bytes either.

    """
    try:
        return _parse(memoryview(raw))
    except (struct.error, ValueError, IndexError):
        pass
    try:
        return deserialize_message(bytes(raw), PointCloud2)
    except Exception as error:   # noqa: BLE001 - rclpy raises several types here
        raise CloudError('malformed_message', f'not a PointCloud2: {error}') from None


_LAYOUTS = {}
"""Field lists by count: (content mask, masked bytes, fields, layout, exact bytes) of
those seen; a stream of clouds repeats one. The padding bytes are masked out: CDR
leaves them unspecified, and serializers do not clear them. A few exact byte strings
of each (padding included) are kept too: a publisher repeats its own, and comparing
bytes costs a tenth of masking them."""

_EXACT = 16
"""Exact byte strings kept per field list."""


def _parse(buf):
    """Parse little-endian CDR; raise ValueError (or struct.error) for anything else."""
    if bytes(buf[0:2]) != _LITTLE_ENDIAN_CDR:
        raise ValueError('not little-endian CDR')
    sec, nanosec = _STAMP.unpack_from(buf, 4)
    frame_id, pos = _string(buf, 12)
    pos += -(pos - 4) % 4
    height, width = _TWO_U32.unpack_from(buf, pos)
    (count,) = _U32.unpack_from(buf, pos + 8)
    pos += 12
    fields, layout, pos = _fields(buf, pos, count)
    is_bigendian = buf[pos]
    pos += 1 + (-(pos + 1 - 4) % 4)
    point_step, row_step = _TWO_U32.unpack_from(buf, pos)
    (size,) = _U32.unpack_from(buf, pos + 8)
    pos += 12
    if pos + size >= len(buf):              # the data, then is_dense
        raise ValueError('data past the end')
    data = buf[pos:pos + size]
    is_dense = buf[pos + size]
    if is_bigendian > 1 or is_dense > 1:
        raise ValueError('a bool that is neither 0 nor 1')
    return Cloud(Header(Stamp(sec, nanosec), frame_id), height, width, fields,
                 bool(is_bigendian), point_step, row_step, data, bool(is_dense), layout)


def _fields(buf, pos, count):
    """Return the ``count`` fields serialized from ``pos`` (4-aligned), their layout, the end."""
    for mask, masked, fields, layout, exact in _LAYOUTS.get(count, ()):
        end = pos + len(mask)
        if end <= len(buf):
            raw = bytes(buf[pos:end])
            if raw in exact:        # bytes seen before, padding included: no masking
                return fields, layout, end
            if np.array_equal(np.frombuffer(buf, np.uint8, len(mask), pos) & mask, masked):
                if len(exact) < _EXACT:
                    exact.add(raw)
                return fields, layout, end
    if count > len(buf) // 13:         # a field takes 13 bytes at least
        raise ValueError('more fields than bytes')
    start, fields, pads = pos, [], []
    for _ in range(count):
        name, pos = _string(buf, pos)
        pads.append((pos, pos + (-(pos - 4) % 4)))
        pos = pads[-1][1]
        (offset,) = _U32.unpack_from(buf, pos)
        datatype = buf[pos + 4]
        pos += 5
        pads.append((pos, pos + (-(pos - 4) % 4)))
        pos = pads[-1][1]
        (field_count,) = _U32.unpack_from(buf, pos)
        pos += 4
        fields.append(Field(name, offset, datatype, field_count))
    fields = tuple(fields)
    layout = tuple((f.name, f.offset, f.datatype, f.count) for f in fields)
    known = _LAYOUTS.setdefault(count, [])
    if len(known) < 8:
        mask = np.full(pos - start, 0xFF, np.uint8)
        for lo, hi in pads:
            mask[lo - start:hi - start] = 0
        known.append((mask, np.frombuffer(buf, np.uint8, pos - start, start) & mask, fields,
                      layout, {bytes(buf[start:pos])}))
    return fields, layout, pos


def _string(buf, pos):
    """Return the string serialized at ``pos`` (4-aligned) and where it ends."""
    (size,) = _U32.unpack_from(buf, pos)
    pos += 4
    if size == 0 or pos + size > len(buf) or buf[pos + size - 1] != 0:
        raise ValueError('string without its NUL or past the end')
    return bytes(buf[pos:pos + size - 1]).decode('utf-8'), pos + size
