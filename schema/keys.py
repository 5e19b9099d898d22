"""The key space as data: every key under `machine/<id>`, who speaks on it, and its models.

One table serves the bus documentation, the JSON Schema export (`machine schema`, written to
`schema/json/keys.json`) and tests. A `<name>` segment stands for any one chunk. Every
queryable may also answer with a failed `Reply` (`success: false`, `error {code, message,
path}`) instead of its reply model.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from pydantic import BaseModel

from .axes import AxisRecord
from .calibration import CalibrationRecord, CalibrationSet
from .commands import REQUEST_MODELS, Command, Reply
from .completion import Completion
from .diag import CycleDiag
from .events import Event, EventPage
from .findings import Findings
from .io import IoValue
from .params import ParamSet, ParamValue
from .sim import SIM_REQUESTS, SimWorldState
from .status import Status


class Direction(StrEnum):
    """How a key is used."""

    REQUEST_REPLY = "request-reply"
    """A queryable: a Rider sends a query (with the request model, if any), the machine replies."""
    PUBLISH = "publish"
    """The machine publishes; Riders subscribe."""
    PUBLISH_AND_QUERY = "publish+query"
    """Published, and a query returns the latest value."""
    LIVELINESS = "liveliness"
    """A liveliness token: present while the machine runs."""


@dataclass(frozen=True)
class KeySpec:
    """One key (relative to `machine/<id>`)."""

    key: str
    direction: Direction
    request: type[BaseModel] | None
    reply: type[BaseModel] | None
    description: str
    sim_only: bool = False

    def as_json(self) -> dict[str, Any]:
        return {
            "key": self.key,
            "direction": self.direction.value,
            "request": None if self.request is None else self.request.__name__,
            "reply": None if self.reply is None else self.reply.__name__,
            "description": self.description,
            "sim_only": self.sim_only,
        }


ERROR_REPLY: type[BaseModel] = Reply
"""What any queryable answers when it refuses a request."""

_R, _P, _PQ = Direction.REQUEST_REPLY, Direction.PUBLISH, Direction.PUBLISH_AND_QUERY

KEYS: tuple[KeySpec, ...] = (
    *(
        KeySpec(f"cmd/{c.key}", _R, REQUEST_MODELS[c], Reply, f"the {c.value} command")
        for c in Command
    ),
    KeySpec("status", _PQ, None, Status, "machine state; on change and every heartbeat"),
    KeySpec("io/<kind>/<name>", _PQ, None, IoValue, "one IO point (kind di, ai or ro)"),
    KeySpec("axis/<name>", _PQ, None, AxisRecord, "FastData-style axis record (rotate, tilt)"),
    KeySpec("diag/cycle", _PQ, None, CycleDiag, "scan-cycle timing, 1 Hz"),
    KeySpec("diag/reset", _R, None, CycleDiag, "reset the timing counters (reply: before)"),
    KeySpec("params/<name>", _R, ParamSet, ParamValue, "an online parameter: get, or set"),
    KeySpec("config/validate", _R, None, Findings, "validate the running or a candidate config"),
    KeySpec(
        "done/<transaction_id>",
        _PQ,
        None,
        Completion,
        "how a motion command ended: once per command; query: IN_PROGRESS / UNKNOWN_TRANSACTION",
    ),
    KeySpec("calibration", _PQ, None, CalibrationRecord, "calibration values, how and when"),
    KeySpec(
        "calibration/set",
        _R,
        CalibrationSet,
        CalibrationRecord,
        "enter calibration values by hand (manual; refused while moving)",
    ),
    KeySpec("events", _R, None, EventPage, "a page of the event history"),
    KeySpec("events/<seq>", _P, None, Event, "each new event, on its own key"),
    KeySpec("alive", Direction.LIVELINESS, None, None, "the machine's liveliness token"),
    KeySpec(
        "holder/<zid>",
        Direction.LIVELINESS,
        None,
        None,
        "the session that holds this machine id; two = two daemons share it (DUPLICATE_ID)",
    ),
    KeySpec(
        "supervisor/<zid>",
        Direction.LIVELINESS,
        None,
        None,
        "the `machine supervise` session that answers for the daemon while it is down",
    ),
    *(
        KeySpec(f"sim/{name}", _R, model, SimWorldState, f"simulator: {name}", sim_only=True)
        for name, model in SIM_REQUESTS.items()
    ),
    KeySpec("sim/world", _R, None, SimWorldState, "simulator: the world's state", sim_only=True),
)
"""Every key of a machine, in documentation order."""


def models() -> dict[str, tuple[type[BaseModel], bool]]:
    """Every model the key space names → (model, used as a request)."""
    out: dict[str, tuple[type[BaseModel], bool]] = {ERROR_REPLY.__name__: (ERROR_REPLY, False)}
    for spec in KEYS:
        if spec.request is not None:
            out[spec.request.__name__] = (spec.request, True)
        if spec.reply is not None:
            out.setdefault(spec.reply.__name__, (spec.reply, False))
    return out


def holder_key(base: str, zid: str) -> str:
    """`machine/<id>/holder/<zid>`: the token naming the session that holds the id."""
    return f"{base}/holder/{zid}"


def supervisor_key(base: str, zid: str) -> str:
    return f"{base}/supervisor/{zid}"


def match(key: str) -> KeySpec | None:
    """The spec of a concrete key relative to `machine/<id>` (e.g. `axis/rotate`), if any."""
    parts = key.split("/")
    for spec in KEYS:
        pattern = spec.key.split("/")
        if len(pattern) == len(parts) and all(
            p == k or (p.startswith("<") and p.endswith(">"))
            for p, k in zip(pattern, parts, strict=True)
        ):
            return spec
    return None


def markdown_table() -> str:
    """The key table as Markdown (docs/schema.md holds it; a test keeps the two equal)."""
    rows = ["| key | direction | request | reply | what |", "|---|---|---|---|---|"]
    for spec in KEYS:
        req = f"`{spec.request.__name__}`" if spec.request else "—"
        rep = f"`{spec.reply.__name__}`" if spec.reply else "—"
        what = spec.description + (" (simulator only)" if spec.sim_only else "")
        rows.append(f"| `{spec.key}` | {spec.direction.value} | {req} | {rep} | {what} |")
    return "\n".join(rows) + "\n"
