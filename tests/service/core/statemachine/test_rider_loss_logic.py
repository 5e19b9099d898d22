"""The rider-loss policy in the state machine: pause, stop, ignore, and the grace period."""

from __future__ import annotations

from pathlib import Path

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.events import RiderEvent
from ride_machine.schema.params import ParamSet
from ride_machine.schema.status import MachineState as S
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.history.events import ListEventSink
from ride_machine.service.core.scan.tasks import RiderPresence
from ride_machine.service.core.statemachine.deadman import Heartbeats
from ride_machine.service.core.storage.params import ParamRegistry
from ride_machine.service.core.storage.persist import ParamStore
from ride_machine.service.errors import ParamOutOfRange
from tests.rig import Rig


def _running(policy: str, grace_s: float = 0.0) -> Rig:
    cfg = MachineConfig().with_overrides(rider_loss={"policy": policy, "grace_s": grace_s})
    rig = Rig(cfg).ready()
    assert rig.send(Command.START, rider="r1").success
    rig.step(5)
    assert rig.relays_on()
    assert rig.state_machine.watch.connected
    return rig


@pytest.mark.hazard("H06")
@pytest.mark.parametrize(
    ("policy", "state"), [("pause", S.PAUSED), ("stop", S.DONE), ("ignore", S.RUNNING)]
)
def test_losing_the_controlling_rider_applies_the_policy(policy: str, state: S) -> None:
    rig = _running(policy)
    rig.state_machine.rider_lost(rig.clock())
    rig.step()
    assert rig.state is state
    assert rig.relays_on() is (state is S.RUNNING)
    assert not rig.state_machine.watch.connected


def test_grace_period_waits_then_pauses() -> None:
    rig = _running("pause", grace_s=0.5)
    rig.state_machine.rider_lost(rig.clock())
    rig.step(int(0.4 / rig.period))
    assert rig.state is S.RUNNING
    rig.run_to_state(S.PAUSED, max_s=0.2)
    assert not rig.relays_on()
    assert rig.state_machine.watch.warning is not None


def test_rider_back_within_grace_changes_nothing() -> None:
    rig = _running("pause", grace_s=0.5)
    rig.state_machine.rider_lost(rig.clock())
    rig.step(10)
    rig.state_machine.rider_back()
    rig.step(int(1.0 / rig.period))
    assert rig.state is S.RUNNING
    assert rig.state_machine.watch.connected


def test_loss_outside_motion_does_nothing() -> None:
    rig = Rig().ready()
    rig.state_machine.rider_lost(rig.clock())
    rig.step(10)
    assert rig.state is S.IDLE


def test_resume_by_another_rider_clears_the_rider_lost_warning() -> None:
    rig = _running("pause")
    rig.state_machine.rider_lost(rig.clock())
    rig.step()
    assert rig.state_machine.watch.warning is not None
    assert rig.send(Command.RESUME, rider="r2").success
    assert rig.state_machine.watch.warning is None
    assert rig.state_machine.controller_rider == "r2"


def _supervised(timeout_s: float = 0.5, grace_s: float = 0.0) -> tuple[Rig, Heartbeats]:
    """A ride started by r1, its heartbeats (arrival times on the rig's clock) judged."""
    cfg = MachineConfig().with_overrides(rider_loss={"timeout_s": timeout_s, "grace_s": grace_s})
    rig = Rig(cfg).ready()
    beats = Heartbeats()
    rig.loop.beats = beats
    assert rig.send(Command.START, rider="r1").success
    return rig, beats


def _beat_for(rig: Rig, beats: Heartbeats, seconds: float, every: float = 0.1) -> None:
    end = rig.clock() + seconds
    while rig.clock() < end:
        beats.beat("r1", rig.clock())
        rig.step(round(every / rig.period))


def test_a_beating_rider_keeps_the_ride_running() -> None:
    rig, beats = _supervised()
    _beat_for(rig, beats, 3.0)
    assert rig.state is S.RUNNING
    assert rig.state_machine.watch.connected


@pytest.mark.hazard("H07")
def test_a_silent_heartbeat_pauses_within_the_timeout_and_two_cycles() -> None:
    rig, beats = _supervised(timeout_s=0.5)
    _beat_for(rig, beats, 1.0)
    last = beats.last_heartbeat("r1")
    assert last is not None
    took = rig.run_to_state(S.PAUSED, max_s=2.0)
    assert rig.clock() - last <= 0.5 + 2 * rig.period
    assert took > 0
    assert not rig.relays_on()
    assert not rig.state_machine.watch.connected
    assert rig.state_machine.watch.warning is not None


@pytest.mark.hazard("H07")
def test_a_rider_that_never_beats_is_lost_after_the_timeout_from_its_command() -> None:
    rig, _ = _supervised(timeout_s=0.3)
    sent = rig.clock()
    rig.run_to_state(S.PAUSED, max_s=1.0)
    assert 0.3 < rig.clock() - sent <= 0.3 + 2 * rig.period


@pytest.mark.hazard("H06", "H36")
def test_heartbeat_back_reconnects_but_moves_nothing() -> None:
    rig, beats = _supervised(timeout_s=0.3)
    rig.run_to_state(S.PAUSED, max_s=1.0)
    _beat_for(rig, beats, 0.5)
    assert rig.state_machine.watch.connected
    assert rig.state is S.PAUSED
    assert not rig.relays_on()


def test_heartbeat_back_within_grace_changes_nothing() -> None:
    rig, beats = _supervised(timeout_s=0.3, grace_s=1.0)
    rig.step(round(0.5 / rig.period))  # lost, grace running
    assert not rig.state_machine.watch.connected
    _beat_for(rig, beats, 2.0)
    assert rig.state is S.RUNNING
    assert rig.state_machine.watch.connected


def test_timeout_is_an_online_parameter_checked_against_the_heartbeat() -> None:
    from ride_machine.service.config.validate import semantic_findings

    ok = MachineConfig()
    assert not [f for f in semantic_findings(ok) if "rider_loss" in f.path]
    bad = MachineConfig().with_overrides(rider_loss={"timeout_s": 0.15})
    found = [f for f in semantic_findings(bad) if f.path == "/rider_loss/timeout_s"]
    assert found and found[0].severity == "error", found
    slow = MachineConfig().with_overrides(loop={"period_s": 0.2}, rider_loss={"timeout_s": 0.3})
    assert any("scan periods" in f.message for f in semantic_findings(slow))


@pytest.mark.hazard("H07")
def test_an_online_timeout_below_two_heartbeats_is_refused(tmp_path: Path) -> None:
    registry = ParamRegistry(MachineConfig(), ParamStore(tmp_path))
    with pytest.raises(ParamOutOfRange, match="heartbeat"):
        registry.set(
            "rider_loss.timeout_s", ParamSet(transaction_id="t1", value=0.15), moving=True, now=0
        )
    assert registry.config.rider_loss.timeout_s == 0.5
    done = registry.set(
        "rider_loss.timeout_s", ParamSet(transaction_id="t2", value=0.45), moving=True, now=0
    )
    assert done.value == 0.45 and registry.config.rider_loss.timeout_s == 0.45


def _departures(sink: ListEventSink) -> list[RiderEvent]:
    return [e for e, _, _ in sink.events if isinstance(e, RiderEvent) and e.kind == "rider_lost"]


def _homed_by_a_beating_rider() -> tuple[Rig, Heartbeats, ListEventSink]:
    """r1 sent Home and beat until it was done (timeout 0.3 s); the events recorded."""
    sink = ListEventSink()
    rig = Rig(MachineConfig().with_overrides(rider_loss={"timeout_s": 0.3}), events=sink).ready()
    beats = Heartbeats()
    rig.loop.beats = beats
    assert rig.send(Command.HOME, rider="r1").success
    while rig.state is S.HOMING:
        _beat_for(rig, beats, 0.2)
    return rig, beats, sink


def test_a_rider_silent_after_its_motion_ended_left_at_rest() -> None:
    """`rider start --wait` ends its session after DONE: the record says nothing was moving."""
    rig, _, sink = _homed_by_a_beating_rider()
    assert rig.state is S.IDLE
    rig.step(round(0.5 / rig.period))  # silent now
    assert not rig.state_machine.watch.connected
    [gone] = _departures(sink)
    assert (gone.rider, gone.acted, gone.mid_motion) == ("r1", False, False)
    assert rig.state is S.IDLE


@pytest.mark.parametrize(("policy", "acted"), [("pause", True), ("stop", True), ("ignore", False)])
def test_a_rider_silent_mid_motion_is_recorded_as_lost_mid_motion(policy: str, acted: bool) -> None:
    sink = ListEventSink()
    cfg = MachineConfig().with_overrides(rider_loss={"timeout_s": 0.3, "policy": policy})
    rig = Rig(cfg, events=sink).ready()
    assert rig.send(Command.START, rider="r1").success
    rig.loop.beats = Heartbeats()  # it never beats
    rig.step(round(0.5 / rig.period))
    [gone] = _departures(sink)
    assert (gone.acted, gone.mid_motion) == (acted, True)


def test_a_heartbeat_that_arrives_after_the_riders_token_went_brings_nothing_back() -> None:
    """A heartbeat sent just before the Rider closed can arrive after its token's going
    (another priority, another queue): it is no sign of life. It made the deadman take the
    Rider back and lose it a second time, one more `rider_lost` in the history (run 21)."""
    rig, beats, sink = _homed_by_a_beating_rider()
    beats.forget("r1")  # the token went (LoopPort.rider_gone), then the task runs
    RiderPresence("r1", alive=False).run(rig.loop, rig.clock())
    beats.beat("r1", rig.clock())  # the overtaken heartbeat
    rig.step(round(1.0 / rig.period))
    assert not rig.state_machine.watch.connected
    assert [(e.rider, e.acted) for e in _departures(sink)] == [("r1", False)]
    beats.returned("r1")  # its token is back: its heartbeats count again
    beats.beat("r1", rig.clock())
    rig.step()
    assert rig.state_machine.watch.connected


def test_the_riders_gone_are_remembered_within_a_bound() -> None:
    beats = Heartbeats(limit=2)
    for rider in ("a", "b", "c"):
        beats.forget(rider)
    beats.beat("a", 1.0)  # the oldest forgotten first: a counts again
    beats.beat("c", 1.0)
    assert (beats.last_heartbeat("a"), beats.last_heartbeat("c")) == (1.0, None)


def _forged(n: int, tag: str = "f") -> list[str]:
    """Made-up Rider ids under one station's login: `rider/bay2/*/heartbeat` lets it put any."""
    return [f"bay2/{tag}{i:x}" for i in range(n)]


@pytest.mark.hazard("H33")
def test_made_up_heartbeats_cannot_crowd_out_a_real_riders_ride() -> None:
    """A station put heartbeats for 1024 made-up ids, and keeps them beating: a full table once
    kept every later Rider's heartbeat out, and its supervised ride was judged LOST."""
    cfg = MachineConfig().with_overrides(rider_loss={"timeout_s": 0.5})
    rig = Rig(cfg).ready()
    beats = Heartbeats()
    rig.loop.beats = beats
    forged = _forged(beats.limit)
    for rider in forged:
        beats.beat(rider, rig.clock())
    assert rig.send(Command.START, rider="r1").success
    end = rig.clock() + 3.0
    while rig.clock() < end:
        for rider in forged:  # all as fresh as the real one, or fresher
            beats.beat(rider, rig.clock())
        beats.beat("r1", rig.clock())
        assert beats.last_heartbeat("r1") == rig.clock()
        rig.step(round(0.1 / rig.period))
    assert rig.state is S.RUNNING and rig.relays_on()
    assert rig.state_machine.watch.connected and rig.state_machine.watch.warning is None


@pytest.mark.hazard("H33")
def test_a_full_table_drops_the_rider_silent_longest_but_never_the_controller() -> None:
    beats = Heartbeats(limit=3)
    beats.controller = "ctl"
    beats.beat("ctl", 1.0)  # silent longest, but it controls the machine
    beats.beat("a", 2.0)
    beats.beat("b", 3.0)
    beats.beat("a", 4.0)  # a beat moves it to the back: b is now silent longest
    beats.beat("new", 5.0)
    assert [beats.last_heartbeat(r) for r in ("ctl", "a", "b", "new")] == [1.0, 4.0, None, 5.0]
    for i, rider in enumerate(_forged(100)):  # a flood of newcomers, each one fresher
        beats.beat(rider, 6.0 + i)
    assert beats.last_heartbeat("ctl") == 1.0
    assert beats.last_heartbeat("a") is None and beats.last_heartbeat("new") is None


def test_riders_silent_past_the_bound_are_dropped_when_a_newcomer_arrives() -> None:
    beats = Heartbeats(silent_s=10.0)
    beats.controller = "ctl"
    for rider in ("ctl", "old1", "old2"):
        beats.beat(rider, 0.0)
    beats.beat("recent", 5.0)
    beats.beat("new", 10.5)  # not full: only the riders silent past 10 s go
    assert [beats.last_heartbeat(r) for r in ("ctl", "old1", "old2", "recent", "new")] == [
        0.0,
        None,
        None,
        5.0,
        10.5,
    ]
