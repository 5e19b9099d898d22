"""The FastData wire format: layouts, byte order, round trips and tolerant, offset-driven reads."""

from __future__ import annotations

import contextlib
import ctypes
import math
import struct
from dataclasses import fields

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ride_machine.schema.fastdata import (
    AXIS,
    HEADER,
    SERVERDATA_VERSION,
    FastAxisData,
    FastDataError,
    Layout,
    decode,
    decode_fields,
    encode,
    pack_reply,
)

U32 = st.integers(0, 2**32 - 1)
I32 = st.integers(-(2**31), 2**31 - 1)
F64 = st.floats(allow_nan=False)


def sample(axis: int = 0, base: float = 0.0) -> FastAxisData:
    """Every field distinct, so a swapped or shifted field cannot go unnoticed."""
    return FastAxisData(
        pnStatus=0x0000_000D,
        axisnumber=axis,
        drvStat=-7,
        bus_cycle_num=4_000_000_000,
        pCmd=base + 1.5,
        pFb=base + 2.25,
        pExt=base - 3.125,
        cCmd=base + 4.0,
        cFb=base + 5.5,
        vCmd=base - 6.75,
        vFb=base + 7.0,
        aCmd=base + 8.5,
        tAddCmd=base + 9.25,
        tFb=base + 10.0,
    )


class CServerData(ctypes.LittleEndianStructure):
    _fields_ = [(name, ctypes.c_uint32) for name, _ in HEADER.fields]


class CFastAxisData(ctypes.LittleEndianStructure):
    _fields_ = [
        ("pnStatus", ctypes.c_uint32),
        ("axisnumber", ctypes.c_int32),
        ("drvStat", ctypes.c_int32),
        ("bus_cycle_num", ctypes.c_uint32),
        *[
            (n, ctypes.c_double)
            for n in ("pCmd", "pFb", "pExt", "cCmd", "cFb", "vCmd", "vFb", "aCmd", "tAddCmd")
        ],
        ("tFb", ctypes.c_double),
    ]


@pytest.mark.parametrize(("layout", "cstruct"), [(HEADER, CServerData), (AXIS, CFastAxisData)])
def test_layouts_match_c_struct_packing(layout: Layout, cstruct: type[ctypes.Structure]) -> None:
    c_offsets = tuple(getattr(cstruct, name).offset for name, _ in cstruct._fields_)
    assert [name for name, _ in layout.fields] == [name for name, _ in cstruct._fields_]
    assert layout.offsets == c_offsets
    assert layout.size == ctypes.sizeof(cstruct)


def test_axis_record_is_96_bytes_with_doubles_from_offset_16() -> None:
    assert AXIS.size == 96
    assert HEADER.size == 32
    assert AXIS.offsets[4:] == tuple(range(16, 96, 8))


def test_dataclass_fields_are_the_protocol_fields_in_order() -> None:
    assert [f.name for f in fields(FastAxisData)] == [name for name, _ in AXIS.fields]


def test_alignment_pads_like_a_c_compiler() -> None:
    layout = Layout((("a", "i"), ("b", "d"), ("c", "I")))
    assert layout.offsets == (0, 8, 16)
    assert layout.size == 24


def test_every_field_round_trips() -> None:
    records = [sample(0), sample(1, base=100.0)]
    reply = decode(encode(records, version=3, ints=[-1, 2**31 - 1], doubles=[math.pi, -0.0]))
    assert reply.version == 3
    assert reply.axes == tuple(records)
    assert reply.ints == (-1, 2**31 - 1)
    assert reply.doubles == (math.pi, -0.0)
    assert math.copysign(1.0, reply.doubles[1]) == -1.0
    assert reply.axis_struct_size == 96


@given(
    status=U32,
    number=I32,
    drv=I32,
    cycle=U32,
    doubles=st.lists(F64, min_size=10, max_size=10),
    ints=st.lists(I32, max_size=8),
    extra=st.lists(F64, max_size=8),
)
def test_any_values_round_trip(
    status: int,
    number: int,
    drv: int,
    cycle: int,
    doubles: list[float],
    ints: list[int],
    extra: list[float],
) -> None:
    record = FastAxisData(status, number, drv, cycle, *doubles)
    reply = decode(encode([record], ints=ints, doubles=extra))
    assert reply.axes == (record,)
    assert reply.ints == tuple(ints)
    assert reply.doubles == tuple(extra)


def test_nan_and_infinities_survive_bit_for_bit() -> None:
    odd = FastAxisData(1, 0, 0, 0, math.nan, math.inf, -math.inf, 5e-324, 0, 0, 0, 0, 0, 0)
    data = encode([odd])
    assert encode(list(decode(data).axes)) == data


def test_bytes_are_little_endian_and_header_points_at_the_records() -> None:
    rec = sample(2)
    data = encode([rec], ints=[0x01020304])
    version, axes_off, count, size, int_off, int_len, _dbl_off, dbl_len = struct.unpack_from(
        "<8I", data
    )
    assert (version, count, size) == (SERVERDATA_VERSION, 1, 96)
    assert (int_off, int_len, dbl_len) == (32, 1, 0)
    assert data[int_off : int_off + 4] == b"\x04\x03\x02\x01"
    assert axes_off % 8 == 0, "records are aligned for a C reader that casts the buffer"
    assert data[axes_off : axes_off + 4] == bytes([0x0D, 0, 0, 0])
    assert struct.unpack_from("<i", data, axes_off + 4)[0] == 2
    assert struct.unpack_from("<d", data, axes_off + 16)[0] == rec.pCmd
    assert len(data) == axes_off + 96


def test_empty_record_set() -> None:
    reply = decode(encode([]))
    assert reply.axes == ()
    assert reply.version == SERVERDATA_VERSION


# -------------------------------------------------------------- newer writers, older readers
HEADER_V2 = HEADER.extended(("flags", "I"), ("server_time_ns_lo", "I"))
AXIS_V2 = AXIS.extended(("jerk", "d"), ("following_error", "d"), ("mode", "i"))


def newer_reply() -> tuple[bytes, list[FastAxisData]]:
    """A reply as a future server would send it: longer header and longer axis records."""
    records = [sample(0), sample(1, base=50.0)]
    values = [{**r.as_dict(), "jerk": 1e9, "following_error": -0.5, "mode": 42} for r in records]
    data = pack_reply(HEADER_V2, AXIS_V2, values, version=2, ints=[7], doubles=[0.25])
    return data, records


def test_newer_reply_has_longer_records_and_header() -> None:
    data, _ = newer_reply()
    _, axes_off, _, size = struct.unpack_from("<4I", data)
    assert size == AXIS_V2.size > AXIS.size
    assert axes_off > HEADER.size


def test_this_reader_reads_a_newer_longer_reply() -> None:
    data, records = newer_reply()
    reply = decode(data)
    assert reply.version == 2
    assert reply.axes == tuple(records)
    assert reply.ints == (7,)
    assert reply.doubles == (0.25,)
    assert reply.axis_struct_size == AXIS_V2.size


def test_reader_knowing_four_fields_and_short_header_reads_newer_reply() -> None:
    data, records = newer_reply()
    raw = decode_fields(data, header=HEADER.prefix(4), axis=AXIS.prefix(4))
    assert raw.header == {
        "version": 2,
        "axesdata_Offset": raw.header["axesdata_Offset"],
        "numOfAxesStructs": 2,
        "sizeOfAxesStruct": AXIS_V2.size,
    }
    assert raw.axes == [
        {
            "pnStatus": r.pnStatus,
            "axisnumber": r.axisnumber,
            "drvStat": r.drvStat,
            "bus_cycle_num": r.bus_cycle_num,
        }
        for r in records
    ]
    assert raw.ints == ()  # it does not know where the arrays are, and does not guess


def test_hand_written_old_reader_uses_only_offsets_and_sizes() -> None:
    """An independent reader, as an existing client would write it, against a newer reply."""
    data, records = newer_reply()
    _version, offset, count, size = struct.unpack_from("<4I", data, 0)
    got = []
    for i in range(count):
        base = offset + i * size
        status, number = struct.unpack_from("<Ii", data, base)
        p_cmd, p_fb = struct.unpack_from("<2d", data, base + 16)
        got.append((status, number, p_cmd, p_fb))
    assert got == [(r.pnStatus, r.axisnumber, r.pCmd, r.pFb) for r in records]


def test_reader_follows_offsets_wherever_the_sections_are() -> None:
    """Records before the arrays and gaps between sections: only the offsets say where."""
    rec = sample(1)
    axes_off, int_off, dbl_off = 40, 40 + 2 * 104 + 4, 40 + 2 * 104 + 16
    buf = bytearray(dbl_off + 16)
    struct.pack_into("<8I", buf, 0, 9, axes_off, 2, 104, int_off, 2, dbl_off, 2)
    for i in range(2):
        AXIS.pack_into(buf, axes_off + i * 104, {**rec.as_dict(), "axisnumber": i})
        buf[axes_off + i * 104 + 96 : axes_off + (i + 1) * 104] = b"\xff" * 8
    struct.pack_into("<2i", buf, int_off, 11, -12)
    struct.pack_into("<2d", buf, dbl_off, 1.0, 2.0)
    reply = decode(bytes(buf))
    assert [a.axisnumber for a in reply.axes] == [0, 1]
    assert reply.axes[1] == rec
    assert reply.ints == (11, -12)
    assert reply.doubles == (1.0, 2.0)


# ------------------------------------------------------------------------------ bad replies
def _header(**over: int) -> bytearray:
    values = {
        "version": 1,
        "axesdata_Offset": 32,
        "numOfAxesStructs": 0,
        "sizeOfAxesStruct": 96,
        "int_array_Offset": 32,
        "int_array_length": 0,
        "double_array_Offset": 32,
        "double_array_length": 0,
    }
    values.update(over)
    buf = bytearray(32)
    HEADER.pack_into(buf, 0, values)
    return buf


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (b"", "shorter than the header"),
        (bytes(31), "shorter than the header"),
        (bytes(_header(numOfAxesStructs=1)), "axis array of 1 x 96 bytes at offset 32"),
        (bytes(_header(numOfAxesStructs=1, sizeOfAxesStruct=16)) + bytes(16), "needs at least"),
        (bytes(_header(numOfAxesStructs=2**32 - 1)), "runs past"),
        (bytes(_header(numOfAxesStructs=1, axesdata_Offset=2**32 - 1)), "runs past"),
        (bytes(_header(int_array_length=1)), "int array"),
        (bytes(_header(double_array_length=2**31, double_array_Offset=8)), "double array"),
    ],
)
def test_unreadable_replies_raise_a_clear_error(data: bytes, message: str) -> None:
    with pytest.raises(FastDataError, match=message):
        decode(data)


def test_zero_records_need_no_valid_record_size() -> None:
    assert decode(bytes(_header(sizeOfAxesStruct=0))).axes == ()


@given(st.binary(max_size=400))
def test_random_bytes_never_crash_the_decoder(data: bytes) -> None:
    with contextlib.suppress(FastDataError):
        decode(data)


@given(st.binary(min_size=32, max_size=32), st.binary(max_size=300))
def test_random_headers_never_crash_the_decoder(head: bytes, body: bytes) -> None:
    with contextlib.suppress(FastDataError):
        decode(head + body)


def test_reader_layout_must_know_the_axis_array_fields() -> None:
    with pytest.raises(ValueError, match="axis-array fields"):
        decode_fields(encode([]), header=HEADER.prefix(2))
