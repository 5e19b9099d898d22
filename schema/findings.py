"""Findings of a configuration check, as a soft PLC's project validation reports them."""

from __future__ import annotations

from enum import StrEnum

from pydantic import Field

from .base import OpenWireModel


class Severity(StrEnum):
    """An error stops the daemon from starting; a warning does not."""

    ERROR = "error"
    WARNING = "warning"


Scalar = bool | int | float | str | None


class Finding(OpenWireModel):
    """One problem: what kind, how bad, where (JSON pointer into the config), and why.

    The fields of seed 000's validation findings, `extra` included: structured context for
    tools (the value found, the limit it broke, the other key it clashes with)."""

    category: str
    severity: Severity
    path: str
    message: str
    extra: dict[str, Scalar | list[Scalar]] = Field(default_factory=dict)


class Findings(OpenWireModel):
    """The whole report; `ok` is false when any finding is an error.

    Seed 000's `system.validate_project` answers `{ok, errors: [...]}`; here the list is named
    `findings` (it holds warnings too) with the same entries: `findings` ≙ `errors`."""

    ok: bool
    findings: list[Finding]
