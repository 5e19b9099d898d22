"""The FastData UDP reply: a `serverdata` header, two extra arrays and `FastAxisData` records.

Little-endian C structs with natural alignment. Readers locate everything through the header's
offsets and sizes and read only the fields they know, so a newer, longer header or axis record
never breaks an older reader.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import astuple, dataclass, field, fields
from typing import Any, cast

SERVERDATA_VERSION = 1
"""The `version` field of the header this code writes."""

USER_REGISTER_LENGTH = 8
"""Version 1's `int_array` and `double_array` each hold this many user registers."""

INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1

DEFAULT_PORT = 60000
"""The UDP port servers listen on unless configured otherwise."""

MAX_REQUEST_BYTES = 256
"""An axis mask longer than this is refused: cell i (0..255) asks for axis number i + 1."""

Value = int | float

_ALIGN = {"I": 4, "i": 4, "d": 8}


def _round_up(n: int, to: int) -> int:
    return -(-n // to) * to


class FastDataError(ValueError):
    """A reply that cannot be read: too short, or an offset or size pointing outside it."""


@dataclass(frozen=True)
class Layout:
    """A C struct: (name, struct code) in order, natural alignment, little-endian."""

    fields: tuple[tuple[str, str], ...]
    offsets: tuple[int, ...] = field(init=False)
    size: int = field(init=False)

    def __post_init__(self) -> None:
        offsets: list[int] = []
        end = 0
        align = 1
        for _name, code in self.fields:
            a = _ALIGN[code]
            align = max(align, a)
            end = _round_up(end, a)
            offsets.append(end)
            end += struct.calcsize("<" + code)
        object.__setattr__(self, "offsets", tuple(offsets))
        object.__setattr__(self, "size", _round_up(end, align))

    @property
    def alignment(self) -> int:
        return max((_ALIGN[code] for _, code in self.fields), default=1)

    def prefix(self, n: int) -> Layout:
        """The first `n` fields: what a reader built for an older, shorter struct knows."""
        return Layout(self.fields[:n])

    def extended(self, *more: tuple[str, str]) -> Layout:
        """This struct with fields appended, as a newer writer would send it."""
        return Layout(self.fields + more)

    def pack_into(self, buf: bytearray, base: int, values: Mapping[str, Value]) -> None:
        """Write every field at its offset from `base`; a missing value is written as zero."""
        for (name, code), off in zip(self.fields, self.offsets, strict=True):
            struct.pack_into("<" + code, buf, base + off, values.get(name, 0))

    def unpack_from(self, data: bytes, base: int, size: int) -> dict[str, Value]:
        """Read the known fields of a `size`-byte struct at `base`; fields past its end stay out."""
        out: dict[str, Value] = {}
        for (name, code), off in zip(self.fields, self.offsets, strict=True):
            if off + struct.calcsize("<" + code) > size:
                break
            out[name] = struct.unpack_from("<" + code, data, base + off)[0]
        return out


HEADER = Layout(
    (
        ("version", "I"),
        ("axesdata_Offset", "I"),
        ("numOfAxesStructs", "I"),
        ("sizeOfAxesStruct", "I"),
        ("int_array_Offset", "I"),
        ("int_array_length", "I"),
        ("double_array_Offset", "I"),
        ("double_array_length", "I"),
    )
)
"""`serverdata`; the array lengths count elements (int32 / float64), not bytes."""

AXIS = Layout(
    (
        ("pnStatus", "I"),
        ("axisnumber", "i"),
        ("drvStat", "i"),
        ("bus_cycle_num", "I"),
        ("pCmd", "d"),
        ("pFb", "d"),
        ("pExt", "d"),
        ("cCmd", "d"),
        ("cFb", "d"),
        ("vCmd", "d"),
        ("vFb", "d"),
        ("aCmd", "d"),
        ("tAddCmd", "d"),
        ("tFb", "d"),
    )
)
"""`FastAxisData`, 96 bytes in version 1."""


@dataclass(frozen=True, slots=True)
class FastAxisData:
    """One axis record; field names are the protocol's."""

    pnStatus: int
    axisnumber: int
    drvStat: int
    bus_cycle_num: int
    pCmd: float
    pFb: float
    pExt: float
    cCmd: float
    cFb: float
    vCmd: float
    vFb: float
    aCmd: float
    tAddCmd: float
    tFb: float

    def as_dict(self) -> dict[str, Value]:
        return dict(zip(_AXIS_NAMES, astuple(self), strict=True))


_AXIS_NAMES = tuple(f.name for f in fields(FastAxisData))


@dataclass(frozen=True)
class RawReply:
    """A reply read through some reader's layouts: the header and records as name → value."""

    header: dict[str, Value]
    axes: list[dict[str, Value]]
    ints: tuple[int, ...]
    doubles: tuple[float, ...]


@dataclass(frozen=True)
class ServerData:
    """A decoded reply: header version, the extra arrays and the typed axis records."""

    version: int
    axes: tuple[FastAxisData, ...]
    ints: tuple[int, ...] = ()
    doubles: tuple[float, ...] = ()
    axis_struct_size: int = AXIS.size


def encode(
    records: Sequence[FastAxisData],
    version: int = SERVERDATA_VERSION,
    ints: Sequence[int] = (),
    doubles: Sequence[float] = (),
) -> bytes:
    """One reply with this version's header and axis layout."""
    return pack_reply(HEADER, AXIS, [r.as_dict() for r in records], version, ints, doubles)


def pack_reply(
    header: Layout,
    axis: Layout,
    records: Sequence[Mapping[str, Value]],
    version: int,
    ints: Sequence[int] = (),
    doubles: Sequence[float] = (),
) -> bytes:
    """A reply for any header / axis layout (newer ones in tests); each section aligned for C."""
    int_off = _round_up(header.size, 4)
    dbl_off = _round_up(int_off + 4 * len(ints), 8)
    axes_off = _round_up(dbl_off + 8 * len(doubles), axis.alignment)
    buf = bytearray(axes_off + axis.size * len(records))
    values: dict[str, Value] = {
        "version": version,
        "axesdata_Offset": axes_off,
        "numOfAxesStructs": len(records),
        "sizeOfAxesStruct": axis.size,
        "int_array_Offset": int_off,
        "int_array_length": len(ints),
        "double_array_Offset": dbl_off,
        "double_array_length": len(doubles),
    }
    header.pack_into(buf, 0, values)
    struct.pack_into(f"<{len(ints)}i", buf, int_off, *ints)
    struct.pack_into(f"<{len(doubles)}d", buf, dbl_off, *doubles)
    for i, record in enumerate(records):
        axis.pack_into(buf, axes_off + i * axis.size, record)
    return bytes(buf)


def decode(data: bytes) -> ServerData:
    """Read a reply from any server version: raises `FastDataError` if it cannot be read."""
    raw = decode_fields(data)
    size = int(raw.header["sizeOfAxesStruct"])
    axes = tuple(FastAxisData(**cast(dict[str, Any], rec)) for rec in raw.axes)
    return ServerData(
        version=int(raw.header["version"]),
        axes=axes,
        ints=raw.ints,
        doubles=raw.doubles,
        axis_struct_size=size,
    )


def decode_fields(data: bytes, header: Layout = HEADER, axis: Layout = AXIS) -> RawReply:
    """Read a reply through a reader's layouts, using only the offsets and sizes it carries.

    The header layout must know at least the four axis-array fields; records must be at least as
    long as the reader's `axis` layout (longer ones are fine: their extra bytes are skipped).
    """
    names = [name for name, _ in header.fields]
    if names[:4] != [name for name, _ in HEADER.fields[:4]]:
        raise ValueError("a reader's header layout starts with version and the axis-array fields")
    if len(data) < header.size:
        raise FastDataError(f"reply of {len(data)} bytes is shorter than the header")
    head = header.unpack_from(data, 0, header.size)
    count = int(head["numOfAxesStructs"])
    size = int(head["sizeOfAxesStruct"])
    offset = int(head["axesdata_Offset"])
    if count and size < axis.size:
        raise FastDataError(
            f"axis records are {size} bytes; this reader needs at least {axis.size}"
        )
    _check_span(data, "axis array", offset, count, size)
    axes = [axis.unpack_from(data, offset + i * size, size) for i in range(count)]
    ints: tuple[int, ...] = ()
    doubles: tuple[float, ...] = ()
    if "int_array_length" in head:
        n, off = int(head["int_array_length"]), int(head["int_array_Offset"])
        _check_span(data, "int array", off, n, 4)
        ints = struct.unpack_from(f"<{n}i", data, off)
    if "double_array_length" in head:
        n, off = int(head["double_array_length"]), int(head["double_array_Offset"])
        _check_span(data, "double array", off, n, 8)
        doubles = struct.unpack_from(f"<{n}d", data, off)
    return RawReply(header=head, axes=axes, ints=ints, doubles=doubles)


def _check_span(data: bytes, what: str, offset: int, count: int, size: int) -> None:
    if count and offset + count * size > len(data):
        raise FastDataError(
            f"{what} of {count} x {size} bytes at offset {offset} runs past the "
            f"{len(data)}-byte reply"
        )
