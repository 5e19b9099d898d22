"""Typed IO values published on `machine/<id>/io/{di,ai,ro}/<name>`."""

from __future__ import annotations

from enum import StrEnum

from .base import OpenWireModel


class IoKind(StrEnum):
    """Digital input, analog input, relay output."""

    DI = "di"
    AI = "ai"
    RO = "ro"


class IoValue(OpenWireModel):
    """One logical IO point: its value and when it last changed."""

    name: str
    kind: IoKind
    channel: str
    value: bool | int
    time: float
