"""Which events to read: a query from a selector's parameters (`machine/<id>/events?…`) or from
the command line's words (`--since 30m --kind fault_raised`), and the errors of a bad one."""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import TypeVar

from .event_kinds import EventKind
from .event_models import Event


class QueryError(ValueError):
    """A bad query parameter; `param` names it."""

    def __init__(self, param: str, message: str) -> None:
        super().__init__(message)
        self.param = param


@dataclass(frozen=True)
class EventQuery:
    """Which events to read: seq and time ranges (inclusive), kinds, and how many."""

    since: int | None = None
    until: int | None = None
    since_time: float | None = None
    until_time: float | None = None
    kinds: tuple[str, ...] = ()
    limit: int | None = None
    last: int | None = None
    """Only the newest `last` matching events (still oldest first in the page)."""

    @classmethod
    def from_params(cls, params: Mapping[str, str]) -> EventQuery:
        """From a selector's parameters: `since`, `until` (seq), `since_time`, `until_time`
        (Unix seconds), `kind` (comma-separated), `limit`, `last`."""
        known = {"since", "until", "since_time", "until_time", "kind", "limit", "last", "format"}
        for name in params:
            if name not in known:
                raise QueryError(name, f"unknown parameter {name!r}; known: {sorted(known)}")
        if params.get("format", "json").lower() not in ("json", "msgpack"):
            raise QueryError("format", f"format must be json or msgpack, got {params['format']!r}")
        kinds = tuple(k for k in params.get("kind", "").split(",") if k)
        valid = {k.value for k in EventKind}
        for kind in kinds:
            if kind not in valid:
                raise QueryError("kind", f"unknown event kind {kind!r}; known: {sorted(valid)}")
        return cls(
            since=_int(params, "since"),
            until=_int(params, "until"),
            since_time=_float(params, "since_time"),
            until_time=_float(params, "until_time"),
            kinds=kinds,
            limit=_int(params, "limit", minimum=1),
            last=_int(params, "last", minimum=1),
        )

    @classmethod
    def from_text(cls, text: str) -> EventQuery:
        """From a selector's parameter text; `;` (Zenoh's separator) and `&` both separate."""
        return cls.from_params(selector_params(text))

    def matches(self, event: Event) -> bool:
        """Whether `event` is one this query selects (ignoring `limit` and `last`)."""
        return (
            (self.since is None or event.seq >= self.since)
            and (self.until is None or event.seq <= self.until)
            and (self.since_time is None or event.time >= self.since_time)
            and (self.until_time is None or event.time <= self.until_time)
            and (not self.kinds or event.kind in self.kinds)
        )

    def params(self) -> str:
        """The selector parameters that ask for this query."""
        parts = []
        for name in ("since", "until", "since_time", "until_time", "limit", "last"):
            value = getattr(self, name)
            if value is not None:
                parts.append(f"{name}={value}")
        if self.kinds:
            parts.append("kind=" + ",".join(self.kinds))
        return ";".join(parts)


def selector_params(text: str) -> dict[str, str]:
    """A selector's parameters, split at `;` (Zenoh's separator) and at `&`."""
    params: dict[str, str] = {}
    for pair in re.split("[;&]", text):
        if pair:
            name, _, value = pair.partition("=")
            params[name] = value
    return params


_T = TypeVar("_T", int, float)

MAX_INT = 2**63 - 1
"""The largest seq, limit or count a query may name (SQLite's INTEGER)."""


def _int(params: Mapping[str, str], name: str, minimum: int = 0) -> int | None:
    value = _parsed(params, name, int, "an integer")
    if value is None:
        return None
    if value < minimum:
        raise QueryError(name, f"{name} must be at least {minimum}, got {value}")
    if value > MAX_INT:
        raise QueryError(name, f"{name} must be at most {MAX_INT}, got {value}")
    return value


def _float(params: Mapping[str, str], name: str) -> float | None:
    value = _parsed(params, name, float, "Unix seconds")
    if value is not None and math.isnan(value):
        raise QueryError(name, f"{name} must be Unix seconds, got {params[name]!r}")
    return value


def _parsed(
    params: Mapping[str, str], name: str, parse: Callable[[str], _T], what: str
) -> _T | None:
    """Parameter `name` parsed (None when absent or empty); a `QueryError` that says `what`
    it must be when it does not parse."""
    text = params.get(name)
    if text is None or text == "":
        return None
    try:
        return parse(text)
    except ValueError:
        raise QueryError(name, f"{name} must be {what}, got {text!r}") from None


AGE_UNITS = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0, "w": 7 * 86400.0}


def parse_point(text: str, now: float) -> tuple[int | None, float | None]:
    """`--since`/`--until`: (seq, None) for a number, (None, Unix time) for an age or a time."""
    text = text.strip()
    if text.isascii() and text.isdigit():
        if int(text) > MAX_INT:
            raise ValueError(f"{text!r} is past the largest seq number ({MAX_INT})")
        return int(text), None
    unit = AGE_UNITS.get(text[-1:].lower())
    if unit is not None:
        try:
            return None, now - float(text[:-1]) * unit
        except ValueError:
            pass
    try:
        return None, datetime.fromisoformat(text).timestamp()
    except ValueError:
        raise ValueError(
            f"{text!r} is neither a seq number, an age (30m, 12h, 7d) nor a time (2026-11-27T14:00)"
        ) from None


def query_of(
    since: str | None,
    until: str | None,
    kinds: Iterable[str],
    now: float,
    last: int | None = None,
) -> EventQuery:
    """A query from command-line words: `--since`/`--until` (see `parse_point`) and `--kind`
    (repeatable, comma-separated); ValueError says what is wrong."""
    s_seq, s_time = parse_point(since, now) if since else (None, None)
    u_seq, u_time = parse_point(until, now) if until else (None, None)
    wanted = tuple(k for arg in kinds for k in arg.split(",") if k)
    known = {k.value for k in EventKind}
    for kind in wanted:
        if kind not in known:
            raise ValueError(f"unknown event kind {kind!r}; known: {', '.join(sorted(known))}")
    return EventQuery(
        since=s_seq, until=u_seq, since_time=s_time, until_time=u_time, kinds=wanted, last=last
    )
