"""The guards' `Facts` read the axes as the status does: `not_home` and `uncalibrated` name the
axes that `homed()` and the calibration say are not, for every combination."""

from __future__ import annotations

import dataclasses
import itertools

import pytest

from ride_machine.schema.status import AxesFlags
from tests.rig import Rig, known_calibration

AXES = ("tilt", "rotate")
FLAGS = list(itertools.product((False, True), repeat=2))
"""(tilt, rotate)."""


def _off(flags: AxesFlags) -> tuple[str, ...]:
    return tuple(a for a in AXES if not getattr(flags, a))


@pytest.mark.parametrize(
    ("refs", "switches"),
    list(itertools.product(FLAGS, FLAGS)),
)
def test_not_home_names_the_axes_homed_says_are_not(
    refs: tuple[bool, bool], switches: tuple[bool, bool]
) -> None:
    rig = Rig(calibration=known_calibration())
    machine = rig.loop.state_machine
    keeper, devices = machine.keeper, machine.devices
    keeper.refs.tilt, keeper.refs.rotate = refs
    di = rig.loop.image.inputs.di
    di[devices.tilt.home.channel], di[devices.rotate.home.channel] = switches
    assert keeper.not_home() == _off(keeper.homed())
    assert machine.facts().not_home == _off(keeper.homed())


@pytest.mark.parametrize("missing", [(), ("tilt",), ("rotate",), ("tilt", "rotate")])
def test_uncalibrated_names_the_axes_without_a_calibration(missing: tuple[str, ...]) -> None:
    cal = dataclasses.replace(known_calibration(), **dict.fromkeys(missing))
    machine = Rig(calibration=cal).loop.state_machine
    assert machine.keeper.uncalibrated() == missing
    assert machine.facts().uncalibrated == missing
