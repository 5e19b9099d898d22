"""`rider calibration [set …]`, `rider params list|get|set|reset` and `rider sim FAULT`: what
an operator sets on the machine (and, on a simulator, the faults it injects). The handlers;
their parsers: rider/subcommands/parsers.py."""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

from pydantic import ValidationError

from ride_machine.rider.blocking import Rider
from ride_machine.rider.exits import EXIT_OK, UsageError
from ride_machine.rider.formats import emit, fmt_calibration, fmt_param, fmt_sim_world
from ride_machine.schema.calibration import RotateCalibrationSet, TiltCalibrationSet


def calibration(args: argparse.Namespace, rider: Rider) -> int:
    """`rider calibration`: the values, and how and when each axis got them."""
    emit(rider.calibration(), args.json, fmt_calibration)
    return EXIT_OK


def set_calibration(args: argparse.Namespace, rider: Rider) -> int:
    """`rider calibration set …`: enter the values by hand."""
    try:
        tilt, rotate = _calibration_values(args)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        raise UsageError(f"calibration value: {first['msg']}") from exc
    record = rider.set_calibration(tilt=tilt, rotate=rotate)
    emit(record, args.json, fmt_calibration)
    return EXIT_OK


def _calibration_values(
    args: argparse.Namespace,
) -> tuple[TiltCalibrationSet | None, RotateCalibrationSet | None]:
    tilt = rotate = None
    if args.tilt_offset is not None or args.tilt_gain is not None:
        if args.tilt_offset is None or args.tilt_gain is None:
            raise UsageError("give both --tilt-offset and --tilt-gain")
        tilt = TiltCalibrationSet(
            offset_counts=args.tilt_offset, gain_counts_per_deg=args.tilt_gain
        )
    if args.rotate_revolution_s is not None or args.rotate_home_arc is not None:
        if args.rotate_revolution_s is None or args.rotate_home_arc is None:
            raise UsageError("give both --rotate-revolution-s and --rotate-home-arc")
        rotate = RotateCalibrationSet(
            revolution_s=args.rotate_revolution_s, home_arc_deg=args.rotate_home_arc
        )
    if tilt is None and rotate is None:
        raise UsageError("give the tilt values, the rotate values, or both")
    return tilt, rotate


def list_params(args: argparse.Namespace, rider: Rider) -> int:
    emit(rider.params(), args.json, lambda vs: "\n".join(fmt_param(p) for p in vs))
    return EXIT_OK


def get_param(args: argparse.Namespace, rider: Rider) -> int:
    emit(rider.param(args.name), args.json, fmt_param)
    return EXIT_OK


def set_param(args: argparse.Namespace, rider: Rider) -> int:
    value = rider.set_param(args.name, _parse_value(args.value), persist=args.persist)
    emit(value, args.json, fmt_param)
    return EXIT_OK


def reset_param(args: argparse.Namespace, rider: Rider) -> int:
    emit(rider.reset_param(args.name), args.json, fmt_param)
    return EXIT_OK


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


SIM_MAX_ARGS = {"home": 2, "tilt_ai": 2, "stall": 2}
"""Words each `rider sim` fault takes (none for the others)."""


def _tilt_ai_args(words: list[str]) -> tuple[bool, float]:
    """`frozen` and/or a noise amplitude in counts; anything else is a typo, not "no fault"."""
    frozen, noise = False, 0.0
    for word in words:
        if word == "frozen":
            frozen = True
            continue
        try:
            noise = float(word)
        except ValueError:
            noise = math.nan
        if not (math.isfinite(noise) and noise >= 0):
            raise UsageError(f"sim tilt_ai: {word!r} is neither `frozen` nor a noise in counts")
    return frozen, noise


def sim(args: argparse.Namespace, rider: Rider) -> int:
    f, a = args.fault, args.args
    if len(a) > SIM_MAX_ARGS.get(f, 0):
        raise UsageError(f"sim {f}: unexpected {' '.join(a[SIM_MAX_ARGS.get(f, 0) :])!r}")
    if f == "stall" and len(a) > 1 and a[1] not in ("on", "off"):
        raise UsageError(f"sim stall: {a[1]!r} is neither `on` nor `off`")
    try:
        if f == "estop":
            world = rider.sim("estop", pressed=True)
        elif f == "release":
            world = rider.sim("estop", pressed=False)
        elif f == "home":
            stuck = a[1] if len(a) > 1 and a[1] != "none" else None
            world = rider.sim("home", axis=a[0], stuck=stuck)
        elif f == "tilt_ai":
            frozen, noise = _tilt_ai_args(a)
            world = rider.sim("tilt_ai", frozen=frozen, noise_counts=noise)
        elif f == "stall":
            world = rider.sim("stall", axis=a[0], stalled=not (len(a) > 1 and a[1] == "off"))
        else:
            world = rider.sim(f)
    except IndexError as exc:
        raise UsageError(f"sim {f}: missing argument") from exc
    emit(world, args.json, fmt_sim_world)
    return EXIT_OK
