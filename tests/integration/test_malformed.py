"""Every queryable of a running daemon fed bad input through real Zenoh.

Each bad request gets one error reply (code, message, and a JSON-pointer path where a field is
to blame); nothing acts; the daemon stays up and its scan loop keeps cycling.
"""

from __future__ import annotations

import contextlib
import json
import random
from collections.abc import Iterator
from dataclasses import dataclass

import msgpack
import pytest
import zenoh

from ride_machine.rider.client import Rider
from ride_machine.schema.axes import AxisRecord
from ride_machine.schema.codec import MAX_PAYLOAD_BYTES, Format, decode, pack
from ride_machine.schema.commands import Command, Reply, ReplyCode
from ride_machine.schema.diag import CycleDiag
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.findings import Findings
from ride_machine.schema.io import IoValue
from ride_machine.schema.sim import SIM_REQUESTS, SimWorldState
from ride_machine.schema.status import FAULT_STATES, MachineState, Status
from tests.integration.support import (
    STEP_TIMEOUT_S,
    module_machine,
    prepare,
    relays_off,
    wait_cycles,
    wait_revolutions,
)
from tests.procs import Daemon

pytestmark = pytest.mark.integration

BASE = "machine/m1"
QUERY_TIMEOUT_S = 5.0
JSON = Format.JSON.value
RNG = random.Random(20261123)  # fixed: a failure can be replayed byte for byte


@dataclass(frozen=True)
class Bad:
    """A malformed request: what the machine must answer (code, and path when a field is bad)."""

    label: str
    payload: bytes
    encoding: str | None = None
    code: ErrorCode = ErrorCode.BAD_PAYLOAD
    path: str | None = None


def _deep_json() -> bytes:
    return b'{"transaction_id": "deep-1", "x": ' + b"[" * 3000 + b"]" * 3000 + b"}"


BAD_REQUESTS = [
    *(Bad(f"random {n} bytes", RNG.randbytes(n)) for n in (1, 7, 64, 4096)),
    Bad("random 1 MiB", RNG.randbytes(1 << 20), code=ErrorCode.PAYLOAD_TOO_LARGE),
    Bad("over the limit", b"{" + b" " * MAX_PAYLOAD_BYTES + b"}", code=ErrorCode.PAYLOAD_TOO_LARGE),
    Bad("msgpack array", pack([1, 2, 3]), path=""),
    Bad("msgpack integer", pack(7), path=""),
    Bad("msgpack string", pack("home"), path=""),
    Bad("msgpack integer map key", pack({1: "t1"})),
    Bad("msgpack bytes id", pack({"transaction_id": b"t1"}), path="/transaction_id"),
    Bad("msgpack float id", pack({"transaction_id": 1.5}), path="/transaction_id"),
    Bad(
        "msgpack ext id",
        msgpack.packb({"transaction_id": msgpack.ExtType(5, b"xx")}),
        path="/transaction_id",
    ),
    Bad("msgpack bad utf-8", b"\x81\xaetransaction_id\xa2\xff\xfe"),
    Bad("msgpack truncated", pack({"transaction_id": "t1"})[:-2]),
    Bad("msgpack nested 5000 deep", b"\x91" * 5000 + b"\xc0"),
    Bad("json wrong type", b'{"transaction_id": 5}', path="/transaction_id"),
    Bad("json unknown field", b'{"transaction_id": "bad-1", "bogus": 1}', path="/bogus"),
    Bad(
        "json id too long",
        json.dumps({"transaction_id": "x" * 65}).encode(),
        path="/transaction_id",
    ),
    Bad("json id bad chars", b'{"transaction_id": "a b"}', path="/transaction_id"),
    Bad("json timecode string", b'{"transaction_id": "t", "timecode": "now"}', path="/timecode"),
    Bad("json array", b"[1, 2]", JSON, path=""),
    Bad("json string", b'"home"', JSON, path=""),
    Bad("json number", b"42", JSON, path=""),
    Bad("json true", b"true", JSON, path=""),
    Bad("json truncated", b'{"transaction_id": "t1"'),
    Bad("json bad utf-8", b'{"transaction_id": "\xff"}'),
    Bad("json nested 50000 deep", b"[" * 50000),
    Bad("json nested 3000 deep in a field", _deep_json()),
]
"""Bad for every command and every simulator request alike."""

EMPTY = Bad("empty", b"", path="/transaction_id")
JSON_NULL = Bad("json null", b"null", JSON, path="/transaction_id")

BAD_SESSIONS = [
    Bad(
        "steps not a list",
        b'{"transaction_id": "s1", "session": {"steps": 3}}',
        path="/session/steps",
    ),
    Bad("no steps", b'{"transaction_id": "s2", "session": {"steps": []}}', path="/session/steps"),
    Bad(
        "degrees a string",
        b'{"transaction_id": "s3", "session": {"steps": [{"kind": "tilt", "degrees": "x"}]}}',
        path="/session/steps/0/degrees",
    ),
    Bad(
        "degrees NaN",
        b'{"transaction_id": "s4", "session": {"steps": [{"kind": "tilt", "degrees": NaN}]}}',
        path="/session/steps/0/degrees",
    ),
    Bad(
        "zero revolutions",
        b'{"transaction_id": "s5", "session": {"steps": [{"kind": "rotate", "revolutions": 0}]}}',
        path="/session/steps/0/revolutions",
    ),
    Bad(
        "unknown step kind",
        b'{"transaction_id": "s6", "session": {"steps": [{"kind": "fly"}]}}',
        path="/session/steps/0",
    ),
]

BAD_SIM = [
    Bad("estop pressed a list", b'{"pressed": [1]}', path="/pressed"),
    Bad("estop pressed a string", b'{"pressed": "yes"}', path="/pressed"),
    Bad("estop unknown field", b'{"pressed": true, "hard": 1}', path="/hard"),
    Bad("home unknown axis", pack({"axis": "spin"}), path="/axis"),
    Bad("home axis a number", pack({"axis": 3}), path="/axis"),
    Bad("tilt_ai noise negative", b'{"noise_counts": -1}', path="/noise_counts"),
    Bad("stall without axis", b'{"stalled": true}', path="/axis"),
]
SIM_KEY = {"estop": "estop", "home": "home", "tilt_ai": "tilt_ai", "stall": "stall"}

UNKNOWN_COMMAND_KEYS = ["fly", "calibrate", "calibrate/spin", "HOME", "home/now", "check"]
WILDCARD_COMMAND_KEYS = [
    f"{BASE}/cmd/*",
    f"{BASE}/cmd/**",
    f"{BASE}/cmd/ho$*",
    f"{BASE}/cmd/calibrate/*",
    f"{BASE}/cmd/home/**",
    "machine/*/cmd/home",
    "machine/**/home",
]
READ_ONLY: dict[str, type[Status | IoValue | AxisRecord | CycleDiag | SimWorldState]] = {
    "status": Status,
    "io/**": IoValue,
    "axis/**": AxisRecord,
    "diag/cycle": CycleDiag,
    "sim/world": SimWorldState,
}


@dataclass(frozen=True)
class Answer:
    """One reply as it came off the wire."""

    ok: bool
    key: str
    encoding: str
    data: bytes

    def model(self, model: type[Reply]) -> Reply:
        fmt = Format.JSON if self.encoding.startswith(JSON) else Format.MSGPACK
        return decode(model, self.data, fmt)


def ask(
    session: zenoh.Session, key: str, payload: bytes, encoding: str | None = None
) -> list[Answer]:
    kwargs: dict[str, object] = {"payload": payload, "timeout": QUERY_TIMEOUT_S}
    if encoding is not None:
        kwargs["encoding"] = encoding
    answers = []
    for reply in session.get(key, **kwargs):  # type: ignore[arg-type]
        sample = reply.ok if reply.ok is not None else reply.err
        assert sample is not None
        key_expr = str(reply.ok.key_expr) if reply.ok is not None else ""
        answers.append(
            Answer(reply.ok is not None, key_expr, str(sample.encoding), sample.payload.to_bytes())
        )
    return answers


def refusal(session: zenoh.Session, key: str, bad: Bad, *, path: bool = True) -> Reply:
    """The one error reply `key` gives to `bad`; asserts its code and (if `path`) its path."""
    answers = ask(session, key, bad.payload, bad.encoding)
    assert len(answers) == 1, f"{key} <- {bad.label}: {answers}"
    answer = answers[0]
    assert answer.ok, f"{key} <- {bad.label}: an error reply is a Reply sample"
    reply = answer.model(Reply)
    assert not reply.success and reply.code is ReplyCode.RESP_ERROR, (key, bad.label)
    assert reply.error is not None and reply.error.message, (key, bad.label)
    assert reply.error.code is bad.code, f"{key} <- {bad.label}: {reply.error}"
    if path and bad.path is not None:
        assert reply.error.path == bad.path, f"{key} <- {bad.label}: {reply.error}"
    return reply


machine = module_machine("malformed")


@pytest.fixture
def rider(machine: Daemon) -> Iterator[Rider]:
    with machine.rider() as r:
        yield r


@contextlib.contextmanager
def untouched(machine: Daemon, rider: Rider) -> Iterator[None]:
    """Asserts that the block moved nothing, changed no state, and the loop kept cycling."""
    status, world, diag = rider.status(), rider.sim("world"), rider.diag()
    yield
    assert machine.proc.poll() is None, f"daemon died:\n{machine.log()}"
    after = wait_cycles(rider, 10)
    assert (after.state, after.calibrated, after.homed) == (
        status.state,
        status.calibrated,
        status.homed,
    )
    assert after.state not in FAULT_STATES, after
    now = rider.sim("world")
    assert (now.revolutions, now.tilt_deg, now.estop_pressed, now.faults) == (
        world.revolutions,
        world.tilt_deg,
        world.estop_pressed,
        world.faults,
    )
    assert relays_off(rider)
    later = rider.diag()
    cycles, overruns = later.cycles - diag.cycles, later.overruns - diag.overruns
    missed = later.missed_cycles - diag.missed_cycles
    print(f"diag: {cycles} cycles, {overruns} overruns, {missed} missed")
    assert cycles > 0
    # Decoding runs on Zenoh's thread, never on the scan thread: a loop that kept its cycle.
    assert overruns <= cycles // 2


@pytest.mark.hazard("H30")
@pytest.mark.parametrize("command", list(Command), ids=lambda c: c.key)
def test_every_command_refuses_every_malformed_payload(
    machine: Daemon, rider: Rider, command: Command
) -> None:
    key = f"{BASE}/cmd/{command.key}"
    cases = [*BAD_REQUESTS, EMPTY, JSON_NULL]
    if command is Command.START:
        cases += BAD_SESSIONS
    with untouched(machine, rider):
        for bad in cases:
            reply = refusal(rider.session, key, bad)
            assert reply.command == command.value


def test_a_numeric_transaction_id_is_refused_with_the_reason(machine: Daemon, rider: Rider) -> None:
    """Issue 58, point 7: seed 000's `{"transaction_id": 101}` was refused "Input should be a
    valid string"; the difference is argued in docs/seeds.md and the refusal says it."""
    bad = Bad("seed number id", b'{"transaction_id": 101}', path="/transaction_id")
    with untouched(machine, rider):
        reply = refusal(rider.session, f"{BASE}/cmd/home", bad)
    assert reply.error is not None and "a transaction id is a string" in reply.error.message
    assert "collide" in reply.error.message


def test_simulator_requests_refuse_malformed_payloads(machine: Daemon, rider: Rider) -> None:
    with untouched(machine, rider):
        for name in SIM_REQUESTS:
            for bad in BAD_REQUESTS:
                # Paths differ here: a sim request may also miss a required field.
                refusal(rider.session, f"{BASE}/sim/{name}", bad, path=False)
        for bad in BAD_SIM:
            name = bad.label.split()[0]
            refusal(rider.session, f"{BASE}/sim/{SIM_KEY[name]}", bad)
        unknown = refusal(
            rider.session, f"{BASE}/sim/fly", Bad("unknown", b"{}", code=ErrorCode.UNKNOWN_COMMAND)
        )
        assert unknown.error is not None and "estop" in unknown.error.message
        for key in (f"{BASE}/sim/*", "machine/*/sim/estop"):
            # One request must never press every machine's E-stop.
            answers = ask(rider.session, key, b'{"pressed": true}')
            assert answers and not any(a.model(Reply).success for a in answers), key


def test_config_validate_reports_findings_or_refuses_oversize(
    machine: Daemon, rider: Rider
) -> None:
    key = f"{BASE}/config/validate"
    with untouched(machine, rider):
        for bad in [*BAD_REQUESTS, JSON_NULL]:
            answers = ask(rider.session, key, bad.payload, bad.encoding)
            assert len(answers) == 1 and answers[0].ok, bad.label
            if bad.code is ErrorCode.PAYLOAD_TOO_LARGE:
                refused = answers[0].model(Reply)
                assert refused.error is not None and refused.error.code is bad.code
                continue
            fmt = Format.JSON if answers[0].encoding.startswith(JSON) else Format.MSGPACK
            findings = decode(Findings, answers[0].data, fmt)
            assert not findings.ok, bad.label
            assert any(f.severity == "error" for f in findings.findings), bad.label


def test_read_only_keys_ignore_a_payload_and_answer_their_record(
    machine: Daemon, rider: Rider
) -> None:
    """A query on status / io / axis / diag / world takes no payload: garbage is not read."""
    with untouched(machine, rider):
        for suffix, model in READ_ONLY.items():
            for bad in BAD_REQUESTS:
                answers = ask(rider.session, f"{BASE}/{suffix}", bad.payload, bad.encoding)
                assert all(a.ok for a in answers), (suffix, bad.label)
                if suffix != "axis/**":  # axis records exist only once an axis has moved
                    assert answers, (suffix, bad.label)
                for answer in answers:
                    fmt = Format.JSON if answer.encoding.startswith(JSON) else Format.MSGPACK
                    decode(model, answer.data, fmt)


@pytest.mark.parametrize("suffix", UNKNOWN_COMMAND_KEYS)
def test_unknown_command_keys_get_unknown_command(
    machine: Daemon, rider: Rider, suffix: str
) -> None:
    with untouched(machine, rider):
        tid = f"unknown-{suffix.replace('/', '-')}"
        reply = refusal(
            rider.session,
            f"{BASE}/cmd/{suffix}",
            Bad(
                suffix, json.dumps({"transaction_id": tid}).encode(), code=ErrorCode.UNKNOWN_COMMAND
            ),
        )
        assert reply.transaction_id == tid
        assert reply.error is not None and "calibrate/tilt" in reply.error.message


def test_wildcard_command_keys_get_bad_key_and_nothing_acts(machine: Daemon, rider: Rider) -> None:
    payload = b'{"transaction_id": "wild-1"}'
    with untouched(machine, rider):
        for key in WILDCARD_COMMAND_KEYS:
            answers = ask(rider.session, key, payload)
            errors = [a.model(Reply).error for a in answers if not a.ok]
            assert errors, f"{key}: {answers}"
            assert all(e is not None and e.code is ErrorCode.BAD_KEY for e in errors), errors
            assert not [a for a in answers if a.ok and a.key.startswith(f"{BASE}/cmd/")], key
    # The wildcard never reached the machine: its transaction id is still unused.
    fresh = ask(rider.session, f"{BASE}/cmd/check/calibration", payload)
    assert len(fresh) == 1 and fresh[0].model(Reply).success


@pytest.mark.hazard("H30")
def test_a_put_on_a_key_that_acts_does_nothing_and_the_log_says_to_query_it(
    machine: Daemon, rider: Rider
) -> None:
    """`zenoh put` where `zenoh get` was meant: nothing acts, and the log names the key (a line
    a second at most, the puts in between counted: tests/service/bus/test_bus_routes.py)."""
    with untouched(machine, rider):
        for key in (f"{BASE}/cmd/home", f"{BASE}/params/loop.scan_period", f"{BASE}/sim/estop"):
            rider.session.put(key, b'{"transaction_id": "put-1", "pressed": true}')
        rider.session.delete(f"{BASE}/calibration/set")
        assert machine.has_logged(f"event=put_ignored key='{BASE}/cmd/home' kind=put")
    assert "answers queries, not puts" in machine.log()
    # The put used no transaction id: the same one as a query is taken.
    fresh = ask(rider.session, f"{BASE}/cmd/check/calibration", b'{"transaction_id": "put-1"}')
    assert len(fresh) == 1 and fresh[0].model(Reply).success


def test_diag_reset_is_its_own_key_and_refuses_wildcards(machine: Daemon, rider: Rider) -> None:
    since = rider.diag().since
    no_payload = Bad("no payload", b"", code=ErrorCode.BAD_KEY)
    old = refusal(rider.session, f"{BASE}/diag/cycle?reset", no_payload)
    assert old.error is not None and f"{BASE}/diag/reset" in old.error.message
    refusal(rider.session, "machine/*/diag/reset", no_payload)  # would reset every machine
    # A wildcard read that covers the reset key only reads.
    (read,) = ask(rider.session, f"{BASE}/diag/**", b"")
    assert read.ok and read.key == f"{BASE}/diag/cycle"
    assert decode(CycleDiag, read.data, Format.MSGPACK).since == since
    assert rider.diag().since == since


def test_a_refused_payload_does_not_use_up_its_transaction_id(
    machine: Daemon, rider: Rider
) -> None:
    key = f"{BASE}/cmd/check/home"
    refusal(
        rider.session,
        key,
        Bad("bogus", b'{"transaction_id": "spent-1", "bogus": 1}', path="/bogus"),
    )
    answers = ask(rider.session, key, b'{"transaction_id": "spent-1"}')
    assert len(answers) == 1 and answers[0].model(Reply).success


@pytest.mark.hazard("H26")
def test_a_repeated_transaction_id_gets_the_same_reply_and_acts_once(
    machine: Daemon, rider: Rider
) -> None:
    prepare(rider)
    started = rider.start()
    wait_revolutions(rider, started, 1)
    pause = b'{"transaction_id": "dup-pause-1"}'
    first = ask(rider.session, f"{BASE}/cmd/pause", pause)
    assert len(first) == 1 and first[0].model(Reply).code is ReplyCode.RESP_PAUSED
    paused = rider.wait_for(
        {MachineState.PAUSED}, STEP_TIMEOUT_S, after=first[0].model(Reply).timecode
    )
    resumed = rider.resume()
    assert resumed.state is MachineState.RUNNING

    again = ask(rider.session, f"{BASE}/cmd/pause", pause)
    assert again == first, "a repeated id gets the very same reply, byte for byte"
    states = []
    for update in rider.watch(("status",), timeout=STEP_TIMEOUT_S):
        if isinstance(update, Status) and update.time >= resumed.timecode:
            states.append(update.state)
            if update.state is MachineState.DONE:
                break
    assert states[-1] is MachineState.DONE, states
    assert MachineState.PAUSED not in states, "the repeated Pause paused again"
    assert paused.session is not None

    other = ask(rider.session, f"{BASE}/cmd/stop", pause)
    refused = other[0].model(Reply)
    assert refused.error is not None
    assert refused.error.code is ErrorCode.DUPLICATE_TRANSACTION
    assert refused.error.path == "/transaction_id"
    assert rider.status().state is MachineState.DONE, "the refused Stop did nothing"
