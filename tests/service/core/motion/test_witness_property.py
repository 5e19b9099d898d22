"""Calibrations typed wrong are found out before they move the tilt wrong (issue 53): over 600
hand-entered tilt calibrations — most with the gain 0.5×–2× the truth and the offset ±10°, the
rest around the witnesses' tolerance or within a hair of the truth — each entered on a
machine found anywhere in its travel, on a host that stalls random scans for up to 50 ms, then
Home and a session to a random angle, on the steppable loop:

- no motion ends DONE with the reported tilt more than 0.5° from the simulator's truth;
- the true tilt never passes `tilt.max_deg` + 1°;
- every calibration wrong by more than 0.5° somewhere in the range is stopped with the code of
  the witness that disagreed (`HOME_OFF_ZERO`, `TILT_GAIN_MISMATCH`, or the short-window speed
  check `TILT_SPEED_IMPLAUSIBLE`), never DONE.

Seeded, on the rig's fake clock: ~20 s of CPU for ~700,000 scan cycles.
"""

from __future__ import annotations

import math
import random
from collections import Counter
from dataclasses import dataclass, field

import pytest

from ride_machine.schema.calibration import CalibrationSet
from ride_machine.schema.commands import Command, RotateStep, Session, TiltStep
from ride_machine.schema.status import FaultCode, MachineState
from ride_machine.service.config.model import MachineConfig
from ride_machine.service.core.motion.devices import Calibration
from ride_machine.sim.settings import PhysicsParams
from tests.rig import WIDE_SCALE, Rig, known_calibration

S = MachineState
C = Command
TRIALS = 600
REPORTED_TOL_DEG = 0.5
OVERRUN_DEG = 1.0
WITNESSES = frozenset(
    {FaultCode.HOME_OFF_ZERO, FaultCode.TILT_GAIN_MISMATCH, FaultCode.TILT_SPEED_IMPLAUSIBLE}
)
"""The codes that say which witness found a calibration wrong."""
SPOILED = frozenset({FaultCode.HOME_EDGE_UNCERTAIN, FaultCode.CALIBRATION_NOT_REPEATABLE})
"""A verification the stalls spoiled: refused, as any measurement that could not be made well."""
MAX_SPOILED = 0.05
RIGHT_DEG = 0.15
"""A calibration within this of the truth all over the range is right: the witnesses must let
most of those ride (they may refuse one the stalls spoiled, or a latch's error tipped over)."""
CONFIG = MachineConfig().with_overrides(
    bus={"ai_deadband_counts": 10_000, "axis_every_cycles": 10_000}, tilt=WIDE_SCALE
)
"""The witnesses alone: a scale as wide as the config allows lets every typed value in."""
MOTIONS = (S.CALIBRATING, S.HOMING, S.RUNNING)


@dataclass
class Tally:
    outcomes: Counter[str] = field(default_factory=Counter)
    worst_done_deg: float = 0.0
    highest_deg: float = -math.inf


def implied_error_deg(world: PhysicsParams, offset: float, gain: float, at_deg: float) -> float:
    """How far the calibration (`offset`, `gain`) reports the tilt from the truth at `at_deg`."""
    raw = world.ai_offset_counts + world.ai_gain_counts_per_deg * at_deg
    return (raw - offset) / gain - at_deg


KINDS = {"wide": (0.70, 1.0, 10.0), "edge": (0.15, 0.012, 0.4), "hair": (0.15, 0.0015, 0.08)}
"""How calibrations are typed: (share, gain factor's spread in log2 or ±, offset's ± degrees):
anywhere in the issue's range; around the witnesses' tolerance; within a hair of the truth."""


def typed(rng: random.Random, world: PhysicsParams, kind: str) -> tuple[float, float]:
    """A calibration as a technician might type it (`KINDS`)."""
    _, spread, shift = KINDS[kind]
    true_gain = world.ai_gain_counts_per_deg
    if kind == "wide":
        factor = 2.0 ** rng.uniform(-spread, spread)
    else:
        factor = 1.0 + rng.uniform(-spread, spread)
    offset = world.ai_offset_counts + rng.uniform(-shift, shift) * true_gain
    return offset, true_gain * factor


def random_world(rng: random.Random) -> PhysicsParams:
    return PhysicsParams(
        start_tilt_deg=rng.uniform(-5.0, CONFIG.tilt.max_deg),
        start_rotate_deg=rng.uniform(0.0, 360.0),
        tilt_home_hysteresis_deg=rng.uniform(0.0, 0.5),
        tilt_noise_counts=rng.uniform(0.0, 2.0),
        scan_stall_probability=rng.uniform(0.0, 0.1),
        scan_stall_max_s=0.05,
        seed=rng.randrange(1 << 30),
    )


def run(rig: Rig, command: Command, tally: Tally, **payload: object) -> S:
    """Run a motion command to its end, following the true tilt every scan."""
    reply = rig.send(command, **payload)
    assert reply.success, reply

    def ended() -> bool:
        tally.highest_deg = max(tally.highest_deg, rig.hal.world.tilt_deg)
        return rig.state not in MOTIONS

    rig.run_until(ended, max_s=120)
    return rig.state


def reported_error(rig: Rig) -> float:
    reported = rig.state_machine.devices.tilt.read_position_degrees()
    assert reported is not None
    return abs(reported - rig.hal.world.tilt_deg)


def trial(rng: random.Random, tally: Tally) -> None:
    world = random_world(rng)
    kind = rng.choices(list(KINDS), [k[0] for k in KINDS.values()])[0]
    offset, gain = typed(rng, world, kind)
    cfg = CONFIG.tilt
    wrong = max(abs(implied_error_deg(world, offset, gain, d)) for d in (cfg.min_deg, cfg.max_deg))
    rig = Rig(
        config=CONFIG.with_overrides(hal={"sim": world.model_dump()}),
        calibration=Calibration(rotate=known_calibration().rotate),
    )
    entry = {"offset_counts": offset, "gain_counts_per_deg": gain}
    rig.state_machine.enter_calibration(
        CalibrationSet.model_validate({"transaction_id": "typed", "tilt": entry}), rig.clock()
    )
    context = (world, offset, gain, f"wrong by {wrong:.2f}°")
    target = round(rng.uniform(cfg.min_deg, cfg.max_deg), 1)
    session = Session(name="p", steps=[TiltStep(degrees=target), RotateStep(revolutions=1)])
    for command, payload in ((C.HOME, {}), (C.START, {"session": session.model_dump()})):
        state = run(rig, command, tally, **payload)
        assert tally.highest_deg <= cfg.max_deg + OVERRUN_DEG, ("overran", context)
        if state is S.FAULT_HW:
            fault = rig.state_machine.fault
            assert fault is not None
            if fault.code in SPOILED:
                tally.outcomes["spoiled: " + fault.code] += 1
                tally.outcomes["right: stopped"] += wrong <= RIGHT_DEG
                return
            assert fault.code in WITNESSES, (fault, context)
            tally.outcomes[f"{kind}: stopped {fault.code}"] += 1
            tally.outcomes["right: stopped"] += wrong <= RIGHT_DEG
            return
        error = reported_error(rig)
        tally.worst_done_deg = max(tally.worst_done_deg, error)
        assert error <= REPORTED_TOL_DEG, (f"{command} DONE {error:.2f}° off the truth", context)
        assert wrong <= REPORTED_TOL_DEG, (f"{command} DONE on a wrong calibration", context)
    tally.outcomes[f"{kind}: session DONE"] += 1
    tally.outcomes["right: DONE"] += wrong <= RIGHT_DEG


@pytest.mark.hazard("H21", "H29")
def test_hand_entered_calibrations_are_verified_or_stopped_never_done_wrong() -> None:
    rng = random.Random(53)
    tally = Tally()
    for _ in range(TRIALS):
        trial(rng, tally)
    outcomes = tally.outcomes
    assert sum(n for k, n in outcomes.items() if not k.startswith("right")) == TRIALS
    spoiled = sum(n for k, n in outcomes.items() if k.startswith("spoiled"))
    assert spoiled <= MAX_SPOILED * TRIALS, outcomes
    # The witnesses pass what is right: calibrations within a hair of the truth ride.
    right = outcomes["right: DONE"] + outcomes["right: stopped"]
    assert right >= 20 and outcomes["right: DONE"] >= 0.9 * right, outcomes
    assert tally.highest_deg <= CONFIG.tilt.max_deg + OVERRUN_DEG
    assert tally.worst_done_deg <= REPORTED_TOL_DEG
