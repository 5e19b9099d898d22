"""Findings of a configuration check, as a soft PLC's project validation reports them."""

from __future__ import annotations

from enum import StrEnum

from schema.base import OpenWireModel


class Severity(StrEnum):
    """An error stops the daemon from starting; a warning does not."""

    ERROR = "error"
    WARNING = "warning"


class Finding(OpenWireModel):
    """One problem: what kind, how bad, where (JSON pointer into the config), and why."""

    category: str
    severity: Severity
    path: str
    message: str


class Findings(OpenWireModel):
    """The whole report; `ok` is false when any finding is an error."""

    ok: bool
    findings: list[Finding]
