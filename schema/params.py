"""Online parameters under `machine/<id>/params/<name>`."""

from __future__ import annotations

from pydantic import FiniteFloat

from .base import OpenWireModel, WireModel
from .commands import TransactionId


class ParamValue(OpenWireModel):
    """A parameter's live value, its project default, and whether a write persisted it."""

    name: str
    value: float | int | bool | str
    default: float | int | bool | str
    persisted: bool
    changed_at: float | None = None
    unit: str = ""
    minimum: float | None = None
    maximum: float | None = None
    locked_while_moving: bool = False
    description: str = ""


class ParamSet(WireModel):
    """Write a parameter (`persist` makes it survive a restart) or reset it to its default."""

    transaction_id: TransactionId
    value: FiniteFloat | int | bool | str | None = None
    """A number is finite: NaN or an infinity is refused at the wire, whatever the parameter."""
    persist: bool = False
    reset: bool = False
