"""Every kind of event reads as a sentence for people (issue 58, point 11): values rounded to what
the instrument resolves, with units, times as times, a Rider as its login and a short id, and
no Python in sight (`rotate None -> {'revolution_s': 4.000109799000256, …} persisted=True`).

The kinds come from the schema's union of details (`KnownDetails`), so a kind added there
without a text here, or without a sample below, fails."""

from __future__ import annotations

import re
from datetime import datetime
from typing import Any, get_args

import pytest
from pydantic import BaseModel

from ride_machine.common.event_words import TEXTS, asker, describe, param_unit, rider_name
from ride_machine.schema import events
from ride_machine.schema.status import MachineState as S
from ride_machine.service.core.storage.params import SPECS

ZID = "9d617a41f205ef9851e789b64de01ca7"
RIDER = f"bay1/{ZID}"
AT = 1796626939.6538846
ROTATE = {"revolution_s": 4.000109799000256, "home_arc_deg": 9.901324136143568}
TILT = {"offset_counts": 1300.0468123, "gain_counts_per_deg": 40.00049871}


def union_kinds() -> set[str]:
    """Every `kind` the schema's details union can carry."""
    union = get_args(events.KnownDetails)[0]
    kinds: set[str] = set()
    for model in get_args(union):
        kinds |= set(get_args(model.model_fields["kind"].annotation))
    return kinds


# (details, what its text must say, the units it must carry): one at least per kind, each with
# the awkward floats a measurement or a wall clock gives.
SAMPLES: list[tuple[BaseModel, str, tuple[str, ...]]] = [
    (
        events.CommandEvent(
            command="Start",
            transaction_id="2a671776-1",
            rider=RIDER,
            identity=RIDER,
            accepted=True,
            code="RESP_START_ACCEPTED",
            state=S.RUNNING,
        ),
        "Start accepted from bay1 · 9d617a, now RUNNING [tx 2a671776-1]",
        (),
    ),
    (
        events.CommandEvent(
            command="CheckHome",
            transaction_id="t9",
            rider=f"anonymous/{ZID}",
            accepted=False,
            code="WRONG_STATE",
            message="not accepted in state RUNNING",
            repeat=True,
        ),
        "Check home refused WRONG_STATE again (a repeat: answered as before, nothing done twice)"
        " from anonymous · 9d617a (claimed): not accepted in state RUNNING [tx t9]",
        (),
    ),
    (
        events.CompletionEvent(
            command="Start",
            transaction_id="2a671776-1",
            outcome="DONE",
            state=S.DONE,
            reason="session complete",
        ),
        "Start finished: DONE (session complete) [tx 2a671776-1]",
        (),
    ),
    (
        events.StateEvent(old=S.RUNNING, new=S.DONE, reason="session complete"),
        "RUNNING → DONE (session complete)",
        (),
    ),
    (
        events.FaultEvent(
            kind="fault_raised", code="TILT_NOT_FOLLOWING", message="stood still", axis="tilt"
        ),
        "TILT_NOT_FOLLOWING raised on the tilt axis: stood still",
        (),
    ),
    (
        events.FaultEvent(kind="fault_cleared", code="TILT_NOT_FOLLOWING", axis="tilt"),
        "TILT_NOT_FOLLOWING cleared on the tilt axis",
        (),
    ),
    (
        events.EstopEvent(kind="estop_pressed", state=S.FAULT_ESTOP),
        "E-stop pressed, machine in FAULT_ESTOP",
        (),
    ),
    (
        events.EstopEvent(kind="estop_released", state=S.FAULT_ESTOP),
        "E-stop released, machine in FAULT_ESTOP",
        (),
    ),
    (
        events.EstopEvent(kind="estop_latched", state=S.FAULT_ESTOP, reason="E-stop pressed"),
        "E-stop latch set (E-stop pressed), machine in FAULT_ESTOP",
        (),
    ),
    (
        events.EstopEvent(kind="estop_reset", state=S.IDLE, reason="Resume"),
        "E-stop latch reset (Resume), machine in IDLE",
        (),
    ),
    (
        events.SessionStartedEvent(
            name="default", steps=2, revolutions_total=3, transaction_id="t3"
        ),
        "“default”: 2 steps, 3 revolutions [tx t3]",
        (),
    ),
    (
        events.SessionEndedEvent(
            name="thrill",
            steps=3,
            steps_done=1,
            revolutions_done=1,
            revolutions_total=5,
            duration_s=187.4987654,
            outcome="STOPPED",
        ),
        "“thrill” STOPPED: 1 of 3 steps, 1 of 5 revolutions in 3 min 07 s",
        ("min", " s"),
    ),
    (
        events.CalibrationEvent(
            axis="rotate", new={**ROTATE, "source": "measured", "at": AT}, persisted=True
        ),
        "rotate calibrated: revolution 4.000 s, home arc 9.9° (measured)",
        (" s", "°"),
    ),
    (
        events.CalibrationEvent(
            axis="tilt",
            old={**TILT, "source": "measured", "at": AT, "verified": True},
            new={
                "offset_counts": 1300.0,
                "gain_counts_per_deg": 40.0,
                "source": "manual",
                "at": AT + 60,
                "verified": False,
            },
            persisted=False,
        ),
        "tilt calibrated: offset 1300.0 counts, gain 40.000 counts/° (manual, not verified yet);"
        " before: offset 1300.0 counts, gain 40.000 counts/°"
        f" (measured, {datetime.fromtimestamp(AT).strftime('%Y-%m-%d %H:%M:%S')});"
        " NOT SAVED: lost at the next restart",
        ("counts", "counts/°"),
    ),
    (
        events.CalibrationEvent(
            axis="rotate", old={**ROTATE, "source": "manual"}, new=None, persisted=True
        ),
        "rotate calibration dropped; before: revolution 4.000 s, home arc 9.9° (manual)",
        (" s", "°"),
    ),
    (
        events.ParamEvent(
            name="tilt.max_deg",
            old=45.0,
            new=50.00000000001,
            persisted=True,
            by=RIDER,
            identity=RIDER,
            transaction_id="p1",
        ),
        "tilt.max_deg set 45° → 50° by bay1 · 9d617a [tx p1]",
        ("°",),
    ),
    (
        events.ParamEvent(name="bus.heartbeat_s", old=2.0, new=1.0, persisted=False, reset=True),
        "bus.heartbeat_s reset to its default 1 s (was 2 s);"
        " NOT SAVED: back to the old value at the next restart",
        (" s",),
    ),
    (
        events.ParamEvent(
            kind="safety_changed",
            name="rider_loss.grace_s",
            old=0.25,
            new=5.123456789,
            persisted=False,
            by=f"anonymous/{ZID}",
            accepted=False,
            message="a safety setting is only made stricter over the bus",
        ),
        "rider_loss.grace_s set 0.25 s → 5.123 s by anonymous · 9d617a (claimed) refused:"
        " a safety setting is only made stricter over the bus",
        (" s",),
    ),
    (
        events.ParamEvent(
            kind="safety_changed", name="rider_loss.policy", old="pause", new="stop", persisted=True
        ),
        "rider_loss.policy set pause → stop",
        (),
    ),
    (
        events.RiderEvent(
            kind="rider_lost", rider=RIDER, policy="pause", acted=True, mid_motion=True
        ),
        "rider bay1 · 9d617a lost mid-motion: policy pause applied",
        (),
    ),
    (
        events.RiderEvent(kind="rider_lost", rider=RIDER, policy="pause", mid_motion=False),
        "rider bay1 · 9d617a left at rest (nothing moving: policy pause not needed)",
        (),
    ),
    (
        events.RiderEvent(kind="rider_returned", rider=RIDER, policy="pause"),
        "rider bay1 · 9d617a back (policy pause)",
        (),
    ),
    (
        events.WatchdogEvent(stalled_s=0.2534567),
        "scan loop stalled 253 ms: outputs forced safe",
        ("ms",),
    ),
    (
        events.ClockEvent(step_s=-11.61234567),
        "host clock set back by 11.6 s (wall times follow it from here)",
        (" s",),
    ),
    (
        events.ClockEvent(step_s=3 * 365 * 86400 + 4000.5),
        "host clock set forward by 1095 d 01 h (wall times follow it from here)",
        (" d", " h"),
    ),
    (
        events.DaemonStartEvent(
            pid=42, hal="sim", period_s=0.010000000000000002, previous_stop_clean=False
        ),
        "pid 42, sim HAL, scan period 10 ms; the previous run did not stop cleanly",
        ("ms",),
    ),
    (
        events.DaemonStopEvent(reason="signal SIGTERM", exit_code=0),
        "signal SIGTERM, exit code 0",
        (),
    ),
    (
        events.StorageEvent(what="events", error="disk I/O error", lost=3),
        "writing events failed: disk I/O error; 3 events lost",
        (),
    ),
    (events.DroppedEvent(count=1), "1 event dropped (the writer's queue was full)", ()),
]

PYTHON_LOOKS = re.compile(r"[{}]|\bNone\b|\bTrue\b|\bFalse\b|\w=\S|'\w+':|->")
"""What only a debugger's dump shows: a dict or its quoted keys, Python's constants, `k=v`."""
NUMBER = re.compile(r"\d+\.(\d+)")
MAX_DECIMALS = 3
"""The finest any event's value resolves: a millisecond, a thousandth of a count per degree."""
LONG_ID = re.compile(r"[0-9a-f]{16,}")
"""A Zenoh session id whole (32 hex digits), where a short one (6) names a Rider."""


def kind_of(details: BaseModel) -> str:
    return str(details.model_dump()["kind"])


def test_every_kind_of_the_schema_has_a_text_and_a_sample_here() -> None:
    kinds = union_kinds()
    assert kinds == set(events.EventKind), "the union and EventKind disagree"
    assert kinds == set(TEXTS), f"no text for {kinds - set(TEXTS)}"
    sampled = {kind_of(details) for details, _, _ in SAMPLES}
    assert kinds == sampled, f"no sample here for {kinds - sampled}"


@pytest.mark.parametrize(
    ("details", "text", "units"), SAMPLES, ids=[kind_of(d) for d, _, _ in SAMPLES]
)
def test_each_kind_reads_for_people(details: Any, text: str, units: tuple[str, ...]) -> None:
    shown = describe(details)
    assert shown == text
    assert not PYTHON_LOOKS.search(shown), shown
    too_fine = [m.group(0) for m in NUMBER.finditer(shown) if len(m.group(1)) > MAX_DECIMALS]
    assert not too_fine, f"more digits than the instrument resolves: {too_fine} in {shown!r}"
    assert not LONG_ID.search(shown) and ZID[6:] not in shown, f"a long id: {shown!r}"
    for unit in units:
        assert unit in shown, f"no unit {unit!r} in {shown!r}"


def test_the_issue_reproduction_reads_as_the_operator_expects() -> None:
    """Issue 58, point 11, word for word."""
    details = events.CalibrationEvent(
        axis="rotate",
        old=None,
        new={**ROTATE, "source": "measured", "at": AT},
        persisted=True,
    )
    assert describe(details) == "rotate calibrated: revolution 4.000 s, home arc 9.9° (measured)"


@pytest.mark.parametrize(
    ("rider", "identity", "name"),
    [
        (RIDER, None, "bay1 · 9d617a"),
        (f"anonymous/{ZID}", None, "anonymous · 9d617a"),
        (ZID, None, "9d617a"),  # schema 1: a bare session id
        (f"bay2/{ZID}", "bay1/e0c2a9d1", "bay1 · e0c2a9"),  # the confirmed one, not the claim
        (None, None, ""),
    ],
)
def test_a_rider_is_named_by_its_login_and_a_short_id(
    rider: str | None, identity: str | None, name: str
) -> None:
    assert rider_name(rider, identity) == name


def test_a_kind_newer_than_this_reader_reads_without_python() -> None:
    text = describe({"kind": "future", "step_s": 1.23456789, "seen": {"x": None, "ok": True}})
    assert text == "step s 1.23457 · seen x none, ok yes"


def test_every_parameter_gets_the_unit_of_the_parameter_table() -> None:
    """The units `param_value` reads off a name are the parameter table's own."""
    for name, spec in SPECS.items():
        assert param_unit(name)[0] == spec.unit, name


def test_a_rider_that_never_confirmed_is_marked_claimed() -> None:
    """Who asked is shown as proven only when the Rider confirmed it (issue 58, point 2)."""
    assert asker(RIDER, RIDER) == "bay1 · 9d617a"
    assert asker(RIDER, None) == "bay1 · 9d617a (claimed)"
    assert asker(None, None) == ""
    assert asker(RIDER, RIDER, "jane") == "bay1 · 9d617a for jane"  # the gateway's OPC UA user
