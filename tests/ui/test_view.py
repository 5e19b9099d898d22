"""`LiveView`: link state, batching and the minute of history, driven with explicit times."""

from __future__ import annotations

import pytest

from ride_machine.rider.ui.view import (
    LOST_AFTER_S,
    NOTICES_KEPT,
    LiveView,
    MachineFound,
    Note,
    Presence,
    Push,
    lost_after,
)
from ride_machine.schema.axes import AxisRecord, PnStatus
from ride_machine.schema.diag import CycleDiag, TimingStats
from ride_machine.schema.io import IoKind, IoValue
from ride_machine.schema.status import MachineState, Status
from tests.schema.completion_samples import done_notice

WALL = 1_700_000_000.0


def status(t: float, state: MachineState = MachineState.IDLE, **kw: object) -> Status:
    return Status.model_validate(
        {"machine_id": "m1", "state": state, "seq": 1, "cycle": 1, "time": WALL + t, **kw}
    )


def axis(name: str, t: float, pos: float, bits: int) -> AxisRecord:
    return AxisRecord(
        axis=name,
        axis_number=1,
        pn_status=bits,
        cycle=1,
        position_cmd=pos,
        position_fb=pos,
        velocity_cmd=0.0,
        velocity_fb=0.0,
        time=WALL + t,
    )


def io(name: str, kind: IoKind, value: bool | int) -> IoValue:
    return IoValue(name=name, kind=kind, channel="X", value=value, time=WALL)


def kinds(events: list[Push]) -> list[str]:
    return [e.kind for e in events]


def test_link_is_down_until_the_first_status_and_says_why() -> None:
    view = LiveView()
    assert not view.link.up
    view.apply(Note("no machine is alive on the network yet; searching…"), 0.0)
    assert "searching" in view.link.reason
    view.apply(MachineFound("m1"), 0.1)
    assert "waiting for machine m1" in view.link.reason
    events = view.apply(status(0.2), 0.2)
    assert kinds(events) == ["status", "link"]
    assert events[1].data == {"up": True, "reason": "", "machine": "m1"}


@pytest.mark.hazard("H08")
def test_link_is_lost_when_the_heartbeat_stops_for_more_than_the_limit() -> None:
    view = LiveView()
    view.apply(MachineFound("m1"), 0.0)
    view.apply(status(0.0), 0.0)
    assert "link" not in kinds(view.tick(LOST_AFTER_S - 0.01, WALL))
    assert view.link.up
    events = view.tick(LOST_AFTER_S + 0.01, WALL)
    assert "link" in kinds(events)
    assert not view.link.up
    assert "no status from machine m1" in view.link.reason
    assert "link" not in kinds(view.tick(LOST_AFTER_S + 0.5, WALL))  # said once, not per tick
    view.apply(status(3.0), 3.0)
    assert view.link.up


@pytest.mark.parametrize(
    ("heartbeat_s", "limit_s"), [(None, 1.5), (1.0, 1.5), (2.0, 3.0), (60.0, 90.0), (0.2, 0.7)]
)
def test_the_limit_follows_the_heartbeat_the_machine_states(
    heartbeat_s: float | None, limit_s: float
) -> None:
    """`bus.heartbeat_s` 2 s: a status every 2 s is a live machine, not a lost one (the
    limit was 1.5 s whatever the machine said); None: a machine too old to say (1 s)."""
    assert lost_after(heartbeat_s or 1.0) == pytest.approx(limit_s)
    view = LiveView()
    view.apply(MachineFound("m1"), 0.0)
    for beat in range(4):  # four heartbeats, each as late as the limit allows
        at = beat * (limit_s - 0.01)
        view.apply(status(at, heartbeat_s=heartbeat_s), at)
        view.tick(at + limit_s - 0.02, WALL)
        assert view.link.up, (beat, view.link.reason)
    last = 3 * (limit_s - 0.01)
    view.tick(last + limit_s + 0.01, WALL)
    assert not view.link.up
    assert f"for over {limit_s:g} s" in view.link.reason


@pytest.mark.hazard("H08")
def test_liveliness_loss_drops_the_link_at_once_and_a_new_status_restores_it() -> None:
    view = LiveView()
    view.apply(MachineFound("m1"), 0.0)
    view.apply(status(0.0), 0.0)
    events = view.apply(Presence(alive=False), 0.1)
    assert kinds(events) == ["link"]
    assert "machine m1 is gone" in view.link.reason
    assert "link" not in kinds(view.tick(1.0, WALL))  # still down: no new status came
    view.apply(Presence(alive=True), 5.0)
    assert not view.link.up  # a token alone is not data yet
    view.apply(status(5.0), 5.0)
    assert view.link.up


def test_digital_io_goes_out_at_once_and_analog_io_is_batched_to_the_tick() -> None:
    view = LiveView()
    view.apply(status(0.0), 0.0)
    assert kinds(view.apply(io("estop", IoKind.DI, True), 0.01)) == ["io"]
    assert kinds(view.apply(io("rotateRelay", IoKind.RO, True), 0.01)) == ["io"]
    for counts in range(100, 200):
        assert view.apply(io("tiltPosition", IoKind.AI, counts), 0.02) == []
    batched = [e for e in view.tick(0.1, WALL) if e.kind == "io"]
    assert len(batched) == 1
    assert batched[0].data[0]["value"] == 199
    assert [e for e in view.tick(0.2, WALL) if e.kind == "io"] == []


def test_gauges_follow_the_axis_stream_while_moving_and_the_status_otherwise() -> None:
    view = LiveView()
    moving = PnStatus.MOVING | PnStatus.DRIVE_ENABLED
    view.apply(status(0.0, tilt_deg=10.0, rotate_deg=None), 0.0)
    view.apply(axis("tilt", 0.5, 12.5, moving), 0.5)
    view.apply(axis("rotate", 0.5, 90.0, moving), 0.5)
    sample = view.sample(WALL + 0.5)
    assert sample["tilt"] == 12.5
    assert sample["rotate"] is None  # the machine does not know the rotate angle yet
    assert sample["tilt_bits"] == int(moving)
    view.apply(status(1.0, tilt_deg=20.0, rotate_deg=45.0), 1.0)
    assert view.sample(WALL + 1.0)["tilt"] == 20.0  # the newer heartbeat wins over old records


def test_history_keeps_one_minute_of_samples_only_while_the_link_is_up() -> None:
    view = LiveView()
    t = 0.0
    for _ in range(800):  # 80 s of ticks with a heartbeat every second
        if round(t * 10) % 10 == 0:
            view.apply(status(t, tilt_deg=5.0), t)
        view.tick(t, WALL + t)
        t = round(t + 0.1, 3)
    samples = list(view.history)
    assert len(samples) <= 601
    assert samples[-1]["t"] - samples[0]["t"] <= 60.0 + 1e-6
    assert samples[-1]["tilt"] == 5.0
    view.apply(Presence(alive=False), t)
    before = len(view.history)
    assert [e for e in view.tick(t + 0.1, WALL + t + 0.1) if e.kind == "sample"] == []
    assert len(view.history) == before


def test_snapshot_has_everything_a_new_page_needs() -> None:
    view = LiveView()
    view.apply(MachineFound("m1"), 0.0)
    view.apply(status(0.0, state=MachineState.RUNNING), 0.0)
    view.apply(io("estop", IoKind.DI, True), 0.0)
    view.apply(
        CycleDiag(
            period_s=0.01,
            cycles=5,
            execution=TimingStats(),
            jitter=TimingStats(),
            overruns=0,
            missed_cycles=0,
            commands=0,
            window=10,
            since=WALL,
            time=WALL,
        ),
        0.0,
    )
    view.tick(0.1, WALL + 0.1)
    snap = view.snapshot(WALL + 0.2)
    assert snap["link"]["up"] is True
    assert snap["status"]["state"] == "RUNNING"
    assert snap["io"][0]["name"] == "estop"
    assert snap["diag"]["period_s"] == 0.01
    assert len(snap["history"]) == 1


def test_calibration_values_reach_the_page_and_its_snapshot() -> None:
    from ride_machine.schema.calibration import CalibrationRecord, CalibrationSource

    view = LiveView()
    record = CalibrationRecord.model_validate(
        {
            "machine_id": "m1",
            "tilt": {"offset_counts": 1194.0, "gain_counts_per_deg": 40.0, "source": "manual"},
            "time": 5.0,
        }
    )
    events = view.apply(record, 1.0)
    assert [e.kind for e in events if e.kind == "calibration"] == ["calibration"]
    snap = view.snapshot(6.0)["calibration"]
    assert snap["tilt"]["source"] == CalibrationSource.MANUAL.value and snap["rotate"] is None


def test_a_completion_notice_is_forwarded_to_the_page() -> None:
    from ride_machine.schema.completion import Completion

    notice = Completion.model_validate(
        {
            "machine_id": "m1",
            "transaction_id": "ui-7",
            "command": "Home",
            "outcome": "DONE",
            "state": "IDLE",
            "started_at": 1.0,
            "time": 2.0,
        }
    )
    events = [e for e in LiveView().apply(notice, 1.0) if e.kind == "done"]
    assert [e.data["transaction_id"] for e in events] == ["ui-7"]


def test_a_snapshot_carries_the_latest_completion_notices_for_a_page_that_was_away() -> None:
    """A page cut off for falling behind reconnects from a snapshot: the notice its command
    waits for may have come meanwhile (a full run under load once left a Start 'accepted')."""
    view = LiveView()
    for i in range(NOTICES_KEPT + 5):
        notice = done_notice(f"t{i}", started_at=float(i))
        [done] = [p for p in view.apply(notice, float(i)) if p.kind == "done"]
        assert done.data["transaction_id"] == f"t{i}"
    kept = view.snapshot(100.0)["done"]
    assert [n["transaction_id"] for n in kept] == [f"t{i}" for i in range(5, NOTICES_KEPT + 5)]
