"""
The readable messages of a damaged MCAP file, record by record.

``rosbags`` reads an MCAP file chunk by chunk through its index and gives up on the
first bad record: a wrong checksum, a length past the end, an unknown opcode or a
chunk that does not decompress loses every message after it. ``salvage_mcap`` walks
the file from the start instead, record by record (the MCAP specification's record
framing: a one-byte opcode, a little-endian uint64 length, the content), skips what it
cannot read and says why, and yields every message it can. It trusts nothing it reads:
each length is checked against what is left.

Reasons (``damage``): ``magic_invalid`` (the file does not start with the MCAP magic),
``record_length_invalid`` (a length past the end of the file or of its chunk: the rest
of that file or chunk is lost, there is no way to find the next record),
``opcode_invalid`` (a reserved opcode: the record is skipped by its length),
``record_unreadable`` (a record whose content does not parse),
``chunk_undecompressable`` (a chunk whose compressed data does not decompress to its
stated size), ``chunk_checksum_mismatch`` (a chunk whose content does not match its
CRC: its records are still read, each message still has to deserialize),
``unknown_channel`` (a message of a channel never defined).

Source: the MCAP format specification (mcap.dev/spec), records Header, Footer, Schema,
Channel, Message, Chunk.
"""

from binascii import crc32
import mmap
import struct
from typing import Callable, Dict, Iterator, Optional, Tuple

MAGIC = b'\x89MCAP0\r\n'
OP_FOOTER, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x02, 0x04, 0x05, 0x06
LAST_OPCODE = 0x0F
"""Opcodes 0x01 to 0x0F are defined; 0x80 and up are private (skipped quietly)."""

_U16 = struct.Struct('<H')
_U32 = struct.Struct('<I')
_U64 = struct.Struct('<Q')
_CHUNK_HEAD = struct.Struct('<QQQI')
_MESSAGE_HEAD = struct.Struct('<HIQQ')

Salvaged = Tuple[str, int, bytes]
"""``(topic, log_time [ns], serialized message)``."""


def _decompress(compression, data, size):
    if compression == '':
        return bytes(data)
    if compression == 'zstd':       # the zstd module rosbags uses (stdlib from 3.14)
        try:
            from compression import zstd
        except ImportError:
            from backports import zstd
        return zstd.decompress(bytes(data))
    if compression == 'lz4':
        from lz4.frame import decompress
        return decompress(bytes(data))
    raise ValueError(f'unknown compression {compression!r}')


def _string(buf, pos):
    (size,) = _U32.unpack_from(buf, pos)
    if pos + 4 + size > len(buf):
        raise ValueError('string past the end')
    return bytes(buf[pos + 4:pos + 4 + size]).decode('utf-8'), pos + 4 + size


def _records(buf, pos, end, damage):
    """Yield ``(opcode, content)`` of the records in ``buf[pos:end]``."""
    while pos < end:
        if pos + 9 > end:
            damage('record_length_invalid')
            return
        opcode = buf[pos]
        (length,) = _U64.unpack_from(buf, pos + 1)
        if length > end - pos - 9:
            damage('record_length_invalid')
            return
        content = buf[pos + 9:pos + 9 + length]
        pos += 9 + length
        if opcode == 0 or LAST_OPCODE < opcode < 0x80:
            damage('opcode_invalid')
            continue
        yield opcode, content


class _Walk:
    """The state of one file's walk: channels seen, where damage goes."""

    def __init__(self, damage: Callable[[str], None], start: Optional[int]) -> None:
        self.damage = damage
        self.start = -1 if start is None else start
        self.channels: Dict[int, str] = {}

    def record(self, opcode, content) -> Iterator[Salvaged]:
        """Yield what one record holds: a message, the messages of a chunk, or nothing."""
        try:
            if opcode == OP_CHANNEL:
                (channel_id,) = _U16.unpack_from(content, 0)
                self.channels[channel_id] = _string(content, 4)[0]
            elif opcode == OP_MESSAGE:
                channel_id, _, log_time, _ = _MESSAGE_HEAD.unpack_from(content, 0)
                if channel_id not in self.channels:
                    self.damage('unknown_channel')
                elif log_time >= self.start:
                    yield self.channels[channel_id], log_time, bytes(
                        content[_MESSAGE_HEAD.size:])
            elif opcode == OP_CHUNK:
                yield from self.chunk(content)
        except (struct.error, ValueError, UnicodeDecodeError):
            self.damage('record_unreadable')

    def chunk(self, content) -> Iterator[Salvaged]:
        """
        Yield the messages of one chunk record, in time order.

        Every chunk is read, also those before ``start``: its channel records may be
        the only definition of the channels of later messages.
        """
        _, _, size, crc = _CHUNK_HEAD.unpack_from(content, 0)
        compression, pos = _string(content, _CHUNK_HEAD.size)
        (length,) = _U64.unpack_from(content, pos)
        if length > len(content) - pos - 8:
            self.damage('record_length_invalid')
            return
        try:
            data = _decompress(compression, content[pos + 8:pos + 8 + length], size)
        except Exception:  # noqa: B902 - zstandard and lz4 raise their own kinds
            self.damage('chunk_undecompressable')
            return
        if len(data) != size:
            self.damage('chunk_undecompressable')
            return
        if crc and crc32(data) != crc:
            self.damage('chunk_checksum_mismatch')
        found = []
        for opcode, record in _records(data, 0, len(data), self.damage):
            found += self.record(opcode, record)
        yield from sorted(found, key=lambda item: item[1])


def salvage_mcap(path: str, damage: Callable[[str], None],
                 start: Optional[int] = None) -> Iterator[Salvaged]:
    """
    Yield every readable message of an MCAP file, in file order (chunks in time order).

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file.
    damage : callable
        ``damage(reason)`` for each skipped record or chunk (the module's reasons).
    start : int, optional
        Only messages with a log time at or after this [ns].

    Yields
    ------
    (str, int, bytes)
        Topic, log time [ns] and the serialized message.

    """
    with open(path, 'rb') as stream:
        try:
            buf = mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ)
        except ValueError:          # an empty file
            damage('magic_invalid')
            return
    with buf:
        if buf[:len(MAGIC)] != MAGIC:
            damage('magic_invalid')
        walk = _Walk(damage, start)
        for opcode, content in _records(buf, len(MAGIC), len(buf), damage):
            if opcode == OP_FOOTER:
                return
            yield from walk.record(opcode, content)
