"""
Read and write ``sensor_msgs/PointCloud2`` rows as numpy columns.

``sensor_msgs_py`` is not available everywhere, and a generic point reader is slower
than one ``np.frombuffer`` with a structured dtype, which is what this does. Fields
are found by name; offsets, ``point_step``, ``row_step`` and endianness come from the
message.
"""

from dataclasses import dataclass

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField


NUMPY_TYPES = {
    PointField.INT8: np.int8,
    PointField.UINT8: np.uint8,
    PointField.INT16: np.int16,
    PointField.UINT16: np.uint16,
    PointField.INT32: np.int32,
    PointField.UINT32: np.uint32,
    PointField.FLOAT32: np.float32,
    PointField.FLOAT64: np.float64,
}
REAL_TYPES = (PointField.FLOAT32, PointField.FLOAT64)
INTEGER_TYPES = (PointField.INT8, PointField.UINT8, PointField.INT16, PointField.UINT16,
                 PointField.INT32, PointField.UINT32)
DATATYPES = {np.dtype(t): code for code, t in NUMPY_TYPES.items()}
MAX_POINT_STEP = 2 ** 31 - 1
"""Largest ``point_step`` read [bytes] (numpy's largest record size)."""


class CloudError(ValueError):
    """A PointCloud2 that cannot be read; ``reason`` names the problem for counters."""

    def __init__(self, reason, detail):
        super().__init__(f'{reason}: {detail}')
        self.reason = reason


@dataclass(frozen=True)
class FieldSpec:
    """A field a reader wants: its name, accepted datatypes and whether it is required."""

    name: str
    datatypes: tuple
    required: bool = True


_DTYPES = {}
"""Structured dtypes by the ``specs`` object's id, then by cloud layout: a stream of
clouds reuses one layout. Each entry holds its ``specs`` (an id is checked against
the object it was made for), so the field specs are not hashed per message."""


def read_columns(msg, specs):
    """
    Return the requested fields of every point as float64 or int64 columns.

    ``columns_of(read_records(msg, specs))``.

    Parameters
    ----------
    msg : sensor_msgs.msg.PointCloud2
        The message to read.
    specs : sequence of FieldSpec
        The fields wanted.

    Returns
    -------
    dict
        ``name -> ndarray, shape (width * height,)``: float64 for real fields, int64
        for integer fields. Optional fields that are absent are left out.

    Raises
    ------
    CloudError
        ``missing_field``, ``unsupported_field_type``, ``point_step_invalid`` (zero
        with points) or ``data_length_mismatch``; nothing else, whatever the layout.

    """
    return columns_of(read_records(msg, specs))


def read_records(msg, specs):
    """
    Return the requested fields of every point as one structured array (no copy).

    Parameters and errors as ``read_columns``. Records of clouds with the same layout
    share one dtype object (cached), so they can be concatenated and converted to
    columns together (``columns_of``).

    Returns
    -------
    ndarray, shape (width * height,)
        Structured, the wanted fields at their offsets, in the cloud's byte order.

    """
    specs = tuple(specs)
    entry = _DTYPES.get(id(specs))
    if entry is None or entry[0] is not specs:
        entry = _DTYPES[id(specs)] = (specs, {})
        if len(_DTYPES) > 16:
            _DTYPES.pop(next(iter(_DTYPES)))
    # ``cloud_bytes.Cloud`` carries its layout as tuples, made once per layout.
    fields = getattr(msg, 'layout', None) or tuple(
        (f.name, f.offset, f.datatype, f.count) for f in msg.fields)
    layout = (fields, msg.point_step, msg.is_bigendian)
    if not 0 <= msg.point_step <= MAX_POINT_STEP or (msg.point_step == 0 and msg.width):
        raise CloudError('point_step_invalid',
                         f'point_step {msg.point_step} for width {msg.width} (1 to '
                         f'{MAX_POINT_STEP} bytes)')
    dtype = entry[1].get(layout)
    if dtype is None:
        dtype = entry[1][layout] = _layout_dtype(msg, specs)
        if len(entry[1]) > 64:
            entry[1].pop(next(iter(entry[1])))
    count = msg.width * msg.height
    if count and msg.row_step < msg.width * msg.point_step:
        raise CloudError('data_length_mismatch',
                         f'row_step {msg.row_step} < width {msg.width} x point_step '
                         f'{msg.point_step}')
    if len(msg.data) != msg.row_step * msg.height:
        raise CloudError('data_length_mismatch',
                         f'{len(msg.data)} bytes of data for height {msg.height} x row_step '
                         f'{msg.row_step}')
    if count == 0:
        return np.empty(0, dtype)
    if msg.height == 1:
        return np.frombuffer(msg.data, dtype, count=msg.width)
    data = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.row_step)
    return data[:, :msg.width * msg.point_step].copy().view(dtype).reshape(-1)


def columns_of(records):
    """Return structured ``records`` as float64 or int64 columns by field name."""
    return {name: records[name].astype(_column_type(records.dtype[name]))
            for name in records.dtype.names}


def _layout_dtype(msg, specs):
    """Return the structured dtype of the wanted fields, or raise CloudError."""
    by_name = {field.name: field for field in msg.fields}
    names, formats, offsets = [], [], []
    for spec in specs:
        field = by_name.get(spec.name)
        if field is None:
            if spec.required:
                raise CloudError('missing_field', f"no field '{spec.name}'")
            continue
        if field.datatype not in spec.datatypes or field.count != 1:
            raise CloudError(
                'unsupported_field_type',
                f"field '{spec.name}' has datatype {field.datatype} x {field.count}")
        dtype = np.dtype(NUMPY_TYPES[field.datatype])
        if field.offset + dtype.itemsize > msg.point_step:
            raise CloudError(
                'data_length_mismatch',
                f"field '{spec.name}' at offset {field.offset} overruns point_step "
                f'{msg.point_step}')
        names.append(spec.name)
        formats.append(dtype.newbyteorder('>' if msg.is_bigendian else '<'))
        offsets.append(field.offset)
    # In offset order, whatever the order of the specs: a structured dtype with fields
    # out of order cannot be exported as a buffer (``read_landmark_clouds`` joins them).
    order = sorted(range(len(names)), key=offsets.__getitem__)
    return np.dtype({'names': [names[k] for k in order],
                     'formats': [formats[k] for k in order],
                     'offsets': [offsets[k] for k in order], 'itemsize': msg.point_step})


def _column_type(dtype):
    return np.float64 if dtype.kind == 'f' else np.int64


class CloudWriter:
    """
    Write rows with a fixed little-endian schema into PointCloud2 messages.

    Fields are laid out in the given order, each aligned to its own size, so the
    whole row is one packed numpy record.

    Parameters
    ----------
    schema : sequence of (str, numpy dtype)
        Field names and types, in order.

    """

    def __init__(self, schema):
        self.names = [name for name, _ in schema]
        offset, formats, offsets = 0, [], []
        for _, dtype in schema:
            dtype = np.dtype(dtype).newbyteorder('<')
            offset = -(-offset // dtype.itemsize) * dtype.itemsize
            formats.append(dtype)
            offsets.append(offset)
            offset += dtype.itemsize
        step = -(-offset // 8) * 8
        self.dtype = np.dtype({'names': self.names, 'formats': formats,
                               'offsets': offsets, 'itemsize': step})
        self.fields = [
            PointField(name=name, offset=off, datatype=DATATYPES[np.dtype(fmt).newbyteorder('=')],
                       count=1)
            for name, fmt, off in zip(self.names, formats, offsets)]

    def rows(self, count):
        """Return a zeroed record array of ``count`` rows to fill column by column."""
        return np.zeros(count, self.dtype)

    def message(self, header, rows, out=None):
        """
        Return a PointCloud2 holding ``rows`` (from ``rows()``) as one unordered row.

        Parameters
        ----------
        header : std_msgs.msg.Header
            Stamp and frame of the message.
        rows : ndarray, structured with this writer's dtype
            The rows to send.
        out : sensor_msgs.msg.PointCloud2, optional
            A message to fill instead of a new one (a publisher may reuse one: it
            serialises the message when it publishes).

        Returns
        -------
        sensor_msgs.msg.PointCloud2

        """
        msg = PointCloud2() if out is None else out
        msg.header = header
        msg.height = 1
        msg.width = len(rows)
        msg.fields = self.fields
        msg.is_bigendian = False
        msg.point_step = self.dtype.itemsize
        msg.row_step = self.dtype.itemsize * len(rows)
        msg.is_dense = True
        msg.data = rows.tobytes()
        return msg
