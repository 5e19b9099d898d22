"""Random command / fault / E-stop / time sequences over thousands of cycles, invariants checked
after every cycle (hypothesis stateful testing).

`STATEFUL_PROFILE=thorough python -m pytest tests/service/core/statemachine/test_stateful.py` runs a
longer search.
"""

from __future__ import annotations

import os
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, rule

from ride_machine.schema.commands import REQUEST_MODELS, Command, Direction, Reply, ReplyCode
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.status import MOTION_STATES, MachineState
from ride_machine.service.core.scan.tasks import PendingCommand
from ride_machine.service.core.statemachine import edges
from ride_machine.sim.physics import SwitchFault
from tests.rig import Rig, known_calibration

settings.register_profile(
    "stateful-ci",
    max_examples=25,
    stateful_step_count=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile(
    "stateful-thorough",
    max_examples=400,
    stateful_step_count=80,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)

S = MachineState
SAFE_STATES = frozenset(S) - MOTION_STATES
"""FAULT_*, PAUSED, DONE, IDLE and WARNING_*: no relay may be on in any of them."""
REFUSALS = frozenset(
    {
        ErrorCode.WRONG_STATE,
        ErrorCode.ESTOP_ACTIVE,
        ErrorCode.NOT_CALIBRATED,
        ErrorCode.NOT_HOME,
        ErrorCode.INVALID_SESSION,
        ErrorCode.DUPLICATE_TRANSACTION,
    }
)

steps = st.one_of(
    st.builds(
        dict,
        kind=st.just("tilt"),
        degrees=st.floats(min_value=-10, max_value=70, allow_nan=False),
    ),
    st.builds(
        dict,
        kind=st.just("rotate"),
        direction=st.sampled_from([d.value for d in Direction]),
        revolutions=st.integers(min_value=1, max_value=2),
    ),
)
sessions = st.one_of(st.none(), st.builds(dict, steps=st.lists(steps, min_size=1, max_size=3)))
FAULTS = ["rotate_open", "rotate_closed", "tilt_open", "tilt_closed", "ai_frozen", "ai_noisy",
          "rotate_stall", "tilt_stall"]  # fmt: skip


class RideMachine(RuleBasedStateMachine):
    """The machine on the simulator, driven by an operator, a fault generator and the clock."""

    rig: Rig

    @initialize(calibrated=st.booleans())
    def power_up(self, calibrated: bool) -> None:
        self.rig = Rig(calibration=known_calibration() if calibrated else None)
        self.first: dict[str, tuple[Command, Reply]] = {}
        self.queued: dict[str, list[Reply]] = {}
        self.tids = 0
        self.cycles = 0
        self.positions = (0.0, 0.0)
        self.check_cycle(moved_allowed=True)

    # ------------------------------------------------------------------------------- rules
    @rule(command=st.sampled_from(list(Command)), session=sessions, reuse=st.integers(0, 5))
    def operator_sends(self, command: Command, session: dict[str, Any] | None, reuse: int) -> None:
        """A command between cycles; sometimes a retry with an id used before."""
        if reuse == 0 and self.first:
            tid = sorted(self.first)[len(self.first) // 2]
        else:
            tid = self.new_tid()
        payload: dict[str, Any] = {"transaction_id": tid}
        if command is Command.START and session is not None:
            payload["session"] = session
        reply = self.rig.send(command, **payload)  # asserts exactly one reply
        self.check_reply(command, tid, reply)

    @rule(command=st.sampled_from(list(Command)))
    def bus_queues_for_next_cycle(self, command: Command) -> None:
        """A command that arrives while a cycle runs: answered by the next cycle."""
        tid = self.new_tid()
        got = self.queued.setdefault(tid, [])
        request = REQUEST_MODELS[command](transaction_id=tid)
        assert self.rig.loop.inbox.put(PendingCommand(command, request, got.append))

    @rule(action=st.sampled_from(["pulse", "pulse", "pulse", "press", "release"]),
          hold=st.integers(0, 120))  # fmt: skip
    def estop(self, action: str, hold: int) -> None:
        """Mostly a press held for some cycles then released; sometimes left pressed."""
        hal = self.rig.hal
        if action == "release":
            hal.release_estop()
            return
        hal.press_estop()
        if action == "pulse":
            for _ in range(hold):
                self.step_and_check()
            hal.release_estop()

    @rule(event=st.sampled_from([*FAULTS, "repair", "repair", "repair"]))
    def hardware(self, event: str) -> None:
        """A sensor or drive fails, or a technician repairs everything."""
        hal = self.rig.hal
        if event == "repair":
            hal.clear_faults()
        elif event.startswith(("rotate_open", "rotate_closed", "tilt_open", "tilt_closed")):
            axis, kind = event.split("_")
            hal.stick_home(
                axis, SwitchFault.STUCK_OPEN if kind == "open" else SwitchFault.STUCK_CLOSED
            )
        elif event == "ai_frozen":
            hal.freeze_tilt_ai()
        elif event == "ai_noisy":
            hal.set_tilt_noise(300)
        else:
            hal.stall(event.split("_", maxsplit=1)[0])

    @rule(session=sessions, cycles=st.integers(0, 1500))
    def operator_goes_for_a_session(self, session: dict[str, Any] | None, cycles: int) -> None:
        """What an operator does to get a ride going: Stop, (calibrate,) Home, Start, watch."""
        rig = self.rig
        for command in (Command.STOP, Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE,
                        Command.HOME):  # fmt: skip
            if command.value.startswith("Calibrate") and rig.state_machine.calibration.complete:
                continue
            self.check_reply(command, tid := self.new_tid(), rig.send(command, transaction_id=tid))
            for _ in range(3000):
                if rig.state not in MOTION_STATES:
                    break
                self.step_and_check()
        payload: dict[str, Any] = {"transaction_id": self.new_tid()}
        if session is not None:
            payload["session"] = session
        self.check_reply(
            Command.START, payload["transaction_id"], rig.send(Command.START, **payload)
        )
        for _ in range(cycles):
            self.step_and_check()

    @rule(hold=st.integers(0, 600), then=st.sampled_from([Command.RESUME, Command.STOP]))
    def operator_pauses(self, hold: int, then: Command) -> None:
        """Pause whatever is going on, wait, then Resume or Stop."""
        rig = self.rig
        self.check_reply(
            Command.PAUSE, tid := self.new_tid(), rig.send(Command.PAUSE, transaction_id=tid)
        )
        for _ in range(hold):
            self.step_and_check()
        self.check_reply(then, tid := self.new_tid(), rig.send(then, transaction_id=tid))

    @rule(cycles=st.sampled_from([1, 2, 10, 50, 200, 600, 1500]))
    def time_passes(self, cycles: int) -> None:
        for _ in range(cycles):
            self.step_and_check()

    # -------------------------------------------------------------------------- checking
    def new_tid(self) -> str:
        self.tids += 1
        return f"h{self.tids}"

    def step_and_check(self) -> None:
        rig = self.rig
        relays_were_on = rig.relays_on()
        rig.step()
        self.cycles += 1
        self.check_cycle(moved_allowed=relays_were_on)

    def check_cycle(self, *, moved_allowed: bool) -> None:
        """What must hold after every scan cycle."""
        rig = self.rig
        state = rig.state
        assert isinstance(state, MachineState)
        on = rig.relays_on()
        if state in SAFE_STATES:
            assert not on, f"relay on in {state}: {rig.hal.outputs}"
        if rig.hal.world.faults.estop_pressed:
            assert state is S.FAULT_ESTOP
            assert not on
            assert not any(rig.loop.image.outputs.ro.values())
        if not moved_allowed:
            world = rig.hal.world
            assert (world.rotate_travel_deg, world.tilt_deg) == self.positions
        self.positions = (rig.hal.world.rotate_travel_deg, rig.hal.world.tilt_deg)
        # Everything queued before this cycle was answered in it, exactly once.
        assert len(rig.loop.inbox) == 0
        for tid, got in self.queued.items():
            assert len(got) == 1, (tid, got)
            assert got[0].transaction_id == tid
        status = rig.loop.published.status
        assert status is not None
        assert status.state is state
        # The latch is set exactly while in FAULT_ESTOP; the input shows the button as it is.
        assert status.estop.latched is (state is S.FAULT_ESTOP)
        assert status.estop.active is rig.hal.world.faults.estop_pressed

    def check_reply(self, command: Command, tid: str, reply: Reply) -> None:
        assert reply.transaction_id == tid
        assert reply.command == command.value
        assert isinstance(reply.state, MachineState)
        assert reply.success is (reply.code is not ReplyCode.RESP_ERROR)
        if reply.success:
            assert reply.error is None
        else:
            assert reply.error is not None
            assert reply.error.code in REFUSALS
            assert reply.error.message
        first = self.first.get(tid)
        if first is None:
            self.first[tid] = (command, reply)
            assert reply.state is self.rig.state
        elif first[0] is command:
            assert reply == first[1]  # a retry: the same answer, nothing done again
        else:
            assert reply.error is not None
            assert reply.error.code is ErrorCode.DUPLICATE_TRANSACTION

    @invariant()
    def state_is_valid(self) -> None:
        assert self.rig.state in set(MachineState)
        # Every state change the machine made is a row of its transition table.
        for change in self.rig.transitions:
            assert (change.old, change.new) in edges(), change
        if self.rig.state in (S.FAULT_HW,):
            assert self.rig.state_machine.fault is not None


PROFILE = "stateful-" + os.environ.get("STATEFUL_PROFILE", "ci")
RideMachine.TestCase.settings = settings.get_profile(PROFILE)
TestRideMachine = RideMachine.TestCase
