"""The FastData client and `rider fastdata`, against a real server on 127.0.0.1."""

from __future__ import annotations

import contextlib
import json
import re
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from ride_machine.rider.fastdata import (
    EXIT_NO_DATA,
    EXIT_OK,
    EXIT_USAGE,
    FastDataClient,
    FastDataUnavailable,
    axis_mask,
    main,
    status_flags,
)
from ride_machine.schema.axes import AxisRecord, PnStatus
from ride_machine.schema.fastdata import (
    AXIS,
    HEADER,
    MAX_REQUEST_BYTES,
    FastAxisData,
    encode,
    pack_reply,
)
from ride_machine.service.adapters.fastdata import FastDataServer, to_fast_axis

DOC = Path(__file__).resolve().parents[2] / "docs" / "fastdata.md"


def record(axis: str, number: int, status: PnStatus) -> AxisRecord:
    k = number - 1
    return AxisRecord(
        axis=axis,
        axis_number=number,
        pn_status=int(status),
        cycle=7,
        position_cmd=45.0 * (k + 1),
        position_fb=44.5 * (k + 1),
        velocity_cmd=-15.0 * k,
        velocity_fb=-14.25 * k,
        time=0.0,
        drive_cmd=3000.0 + 1800.0 * k,
        drive_fb=2980.0 + 1780.0 * k,
    )


AXES = {
    "rotate": record("rotate", 1, PnStatus.SETTLED | PnStatus.DRIVE_ENABLED),
    "tilt": record("tilt", 2, PnStatus.MOVING | PnStatus.DRIVE_ENABLED | PnStatus.DRIVE_FAULT),
}


@pytest.fixture
def server() -> Iterator[FastDataServer]:
    with FastDataServer(lambda: AXES, port=0, cycle=lambda: 1234) as srv:
        yield srv


@pytest.fixture
def silent() -> Iterator[socket.socket]:
    """A bound UDP socket that never answers: the client must time out, not hang."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    try:
        yield sock
    finally:
        sock.close()


@contextmanager
def answering(sock: socket.socket, reply: bytes) -> Iterator[None]:
    """A one-shot fake server on `sock`: answers the first request with `reply`."""

    def serve() -> None:
        with contextlib.suppress(OSError):
            _, peer = sock.recvfrom(MAX_REQUEST_BYTES)
            sock.sendto(reply, peer)

    t = threading.Thread(target=serve)
    t.start()
    try:
        yield
    finally:
        t.join(5)
        assert not t.is_alive()


def port_args(port: int) -> list[str]:
    return ["--port", str(port), "--timeout", "2"]


# -------------------------------------------------------------------------- axis mask
def test_axis_mask_names_axes_by_number_as_the_seed_does() -> None:
    # Seed 002: cells 0, 5 and 13 ask for axes 1, 6 and 14.
    assert axis_mask([1, 6, 14]) == bytes(1 if i in (0, 5, 13) else 0 for i in range(14))
    assert axis_mask([2]) == b"\x00\x01"
    assert axis_mask([1, 2]) == b"\x01\x01"
    assert axis_mask([4, 1]) == b"\x01\x00\x00\x01"
    assert axis_mask(None) == b"\x01" * MAX_REQUEST_BYTES


@pytest.mark.parametrize(("axes", "message"), [([0], "0 outside"), ([257], "257"), ([], "one")])
def test_axis_mask_refuses_bad_indices(axes: list[int], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        axis_mask(axes)


def test_status_flags_name_each_bit() -> None:
    assert status_flags(0) == "-"
    assert status_flags(int(PnStatus.MOVING | PnStatus.DRIVE_ENABLED)) == "moving,enabled"
    assert status_flags(int(PnStatus.DRIVE_FAULT) | 0x60) == "FAULT,0x60"
    assert (
        status_flags(int(PnStatus.POSITION_UNKNOWN | PnStatus.DRIVE_ENABLED)) == "enabled,unknown"
    )


# ----------------------------------------------------------------------------- client
def test_query_returns_typed_records(server: FastDataServer) -> None:
    with FastDataClient("127.0.0.1", server.port, timeout=2.0) as client:
        reply = client.query()
        tilt_only = client.query([2])
    assert reply.axes == (to_fast_axis(AXES["rotate"], 1234), to_fast_axis(AXES["tilt"], 1234))
    (tilt,) = tilt_only.axes
    assert isinstance(tilt, FastAxisData)
    assert (tilt.axisnumber, tilt.pFb, tilt.vFb, tilt.drvStat) == (2, 89.0, -14.25, 1)
    assert tilt.pnStatus & PnStatus.MOVING


def test_timeout_is_a_clear_error(silent: socket.socket) -> None:
    port = silent.getsockname()[1]
    with (
        FastDataClient("127.0.0.1", port, timeout=0.2) as client,
        pytest.raises(FastDataUnavailable, match=f"no reply from 127.0.0.1:{port} within 0.2 s"),
    ):
        client.query([1])
    assert silent.recvfrom(10)[0] == b"\x01"  # the request did go out


def test_closed_port_is_a_clear_error(silent: socket.socket) -> None:
    port = silent.getsockname()[1]
    silent.close()
    with FastDataClient("127.0.0.1", port, timeout=2.0) as client:
        with pytest.raises(FastDataUnavailable, match=f"nothing listens on 127.0.0.1:{port}"):
            client.query([1])
        # The refusal is not remembered into the next query's answer.
        with pytest.raises(FastDataUnavailable, match="nothing listens"):
            client.query([1])


def test_unreadable_reply_is_a_clear_error(silent: socket.socket) -> None:
    with (
        answering(silent, b"\x01\x00"),
        FastDataClient(*silent.getsockname(), 2.0) as client,
        pytest.raises(FastDataUnavailable, match=r"unreadable reply.*shorter than the header"),
    ):
        client.query([1])


def test_late_reply_to_a_timed_out_query_is_not_taken_for_the_next(
    silent: socket.socket,
) -> None:
    late = encode([to_fast_axis(AXES["rotate"], 1)])
    fresh = encode([to_fast_axis(AXES["rotate"], 2)])
    timed_out, late_sent = threading.Event(), threading.Event()

    def slow_server() -> None:
        with contextlib.suppress(OSError):
            _, peer = silent.recvfrom(10)
            if timed_out.wait(5):
                silent.sendto(late, peer)  # the answer to the first query, after its timeout
            late_sent.set()
            _, peer = silent.recvfrom(10)
            silent.sendto(fresh, peer)

    t = threading.Thread(target=slow_server)
    t.start()
    try:
        with FastDataClient(*silent.getsockname(), timeout=0.2) as client:
            with pytest.raises(FastDataUnavailable):
                client.query([1])
            timed_out.set()
            assert late_sent.wait(5)
            client.timeout = 2.0
            assert client.query([1]).axes[0].bus_cycle_num == 2
    finally:
        timed_out.set()
        t.join(5)
    assert not t.is_alive()


def test_client_reads_a_newer_server_with_longer_records(silent: socket.socket) -> None:
    rec = to_fast_axis(AXES["tilt"], 9)
    data = pack_reply(
        HEADER.extended(("extra", "I")),
        AXIS.extended(("jerk", "d")),
        [{**rec.as_dict(), "jerk": 5.0}],
        version=2,
    )
    with answering(silent, data), FastDataClient(*silent.getsockname(), 2.0) as client:
        reply = client.query([2])
    assert reply.axes == (rec,)
    assert reply.version == 2
    assert reply.axis_struct_size == 104


# -------------------------------------------------------------------------------- CLI
ROTATE_TAIL = ["3000.000", "2980.000", "0.000", "0.000"]  # cCmd cFb vCmd vFb
TILT_TAIL = ["4800.000", "4760.000", "-15.000", "-14.250"]


def test_cli_prints_a_table(server: FastDataServer, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(port_args(server.port)) == EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split() for ln in lines] == [
        ["axis", "status", "drvStat", "cycle", "pCmd", "pFb", "cCmd", "cFb", "vCmd", "vFb"],
        ["1", "settled,enabled", "0", "1234", "45.000", "44.500", *ROTATE_TAIL],
        ["2", "moving,enabled,FAULT", "1", "1234", "90.000", "89.000", *TILT_TAIL],
    ]


def test_cli_one_axis_as_json(server: FastDataServer, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([*port_args(server.port), "--axis", "2", "--json"]) == EXIT_OK
    (line,) = capsys.readouterr().out.splitlines()
    assert json.loads(line) == {"version": 1, **to_fast_axis(AXES["tilt"], 1234).as_dict()}


def test_cli_watch_streams_count_polls(
    server: FastDataServer, capsys: pytest.CaptureFixture[str]
) -> None:
    args = [*port_args(server.port), "--watch", "--interval", "0", "--count", "3", "--axis", "1"]
    assert main(args) == EXIT_OK
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("axis")
    assert [ln.split()[0] for ln in lines[1:]] == ["1", "1", "1"]
    server.close()  # joins the server thread: its counters are final
    assert server.stats.replies == 3


def test_cli_without_a_server_exits_1_and_says_why(
    silent: socket.socket, capsys: pytest.CaptureFixture[str]
) -> None:
    port = silent.getsockname()[1]
    assert main(["--port", str(port), "--timeout", "0.2"]) == EXIT_NO_DATA
    out = capsys.readouterr()
    assert out.out == ""
    assert f"no reply from 127.0.0.1:{port}" in out.err


def test_cli_watch_keeps_going_after_a_miss(
    silent: socket.socket, capsys: pytest.CaptureFixture[str]
) -> None:
    port = silent.getsockname()[1]
    args = ["--port", str(port), "--timeout", "0.1", "--watch", "--interval", "0", "--count", "2"]
    assert main(args) == EXIT_NO_DATA
    assert capsys.readouterr().err.count("no reply") == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--axis", "300"], "300 outside"),
        (["--port", "0"], "--port 0 outside"),
        (["--timeout", "0"], "--timeout"),
        (["--watch", "--count", "0"], "--count"),
        (["--interval", "-1"], "--interval"),
        (["--watch", "--interval", "nan"], "--interval must be >= 0 and finite"),
        (["--watch", "--interval", "inf"], "--interval must be >= 0 and finite"),
        (["--timeout", "nan"], "--timeout must be > 0 and finite"),
    ],
)
def test_cli_bad_options_exit_2(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(args) == EXIT_USAGE
    assert message in capsys.readouterr().err


def test_cli_host_that_does_not_resolve_is_a_clear_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["--host", "no-such-host.invalid", "--timeout", "0.2"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("rider fastdata: cannot reach no-such-host.invalid:60000: ")


# ------------------------------------------------------------------------------- docs
def _doc_python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.DOTALL)


def test_docs_examples_run_against_a_live_server(server: FastDataServer) -> None:
    blocks = _doc_python_blocks()
    assert len(blocks) == 2
    for block in blocks:
        assert "60000" in block
        code = block.replace("60000", str(server.port))
        done = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            timeout=30,
            cwd=DOC.parents[1],
            check=False,
        )
        assert done.returncode == 0, done.stderr
        assert "89.0" in done.stdout or "pos 89.00" in done.stdout


def test_docs_table_matches_the_record_layout() -> None:
    rows = re.findall(r"^\| (\d+) \| (\w+) \| `(\w+)` \|", DOC.read_text(), flags=re.MULTILINE)
    expected = [
        (off, name)
        for layout in (HEADER, AXIS)
        for off, (name, _) in zip(layout.offsets, layout.fields, strict=True)
    ]
    assert [(int(o), n) for o, _, n in rows] == expected
