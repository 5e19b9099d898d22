"""At most once across a restart: the answers of recent commands, read back from the event history.

The scan loop remembers the last `bus.transaction_window` replies by transaction id (a retry gets
the first reply; service/core/commands/transactions.py) and the completion notices (`done/<id>`);
both lived in memory only, so a Start answered and run to DONE, the daemon restarted, and the same
request sent again started a second ride. Every command the loop answers is also a `command` event
in `<data_dir>/events.db` (id, command, accepted, code, message, state), and every motion's end a
`completion` event: at start-up the daemon reads the newest of them back and fills both memories, so
a repeat after a restart gets the recorded outcome, not a second motion.

How far back it holds: the newest `bus.transaction_window` commands (4096 by default) that the
history still keeps (its retention, `[events]`), as in memory. What the history never got is
not recalled: `[events] enabled = false`, a database that could not be written, or the last
milliseconds before a SIGKILL or a power cut (the history's process writes within ~20 ms).
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from ride_machine.schema import SCHEMA_VERSION
from ride_machine.schema.codec import pack
from ride_machine.schema.commands import ReplyCode
from ride_machine.schema.completion import Completion
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.events import CompletionEvent
from ride_machine.schema.status import MachineState

from .eventdb import WRITER_WAIT_S, claim_writer, connect_readonly

log = logging.getLogger(__name__)

_NEWEST = (
    "SELECT time, details FROM events WHERE kind = ? AND machine_id = ? ORDER BY seq DESC LIMIT ?"
)


@dataclass
class Recalled:
    """The replies of recent commands, and their completion notices."""

    replies: list[tuple[str, str, bytes]] = field(default_factory=list)
    """(transaction id, command, its reply as msgpack), oldest first."""
    completions: list[Completion] = field(default_factory=list)
    since: float | None = None
    """When the oldest recalled command was answered (wall time)."""


def recall(path: Path, machine_id: str, window: int, wait_s: float = WRITER_WAIT_S) -> Recalled:
    """The newest `window` first answers and notices in the history at `path` (nothing when it
    cannot be read: said in the log, the daemon starts all the same). Read once the previous
    run's writer has let go of it (at most `wait_s`): its last events are in."""
    fd, _ = claim_writer(path, wait_s) if path.exists() else (None, None)
    try:
        return _read(path, machine_id, window)
    finally:
        if fd is not None:
            os.close(fd)


def _read(path: Path, machine_id: str, window: int) -> Recalled:
    out = Recalled()
    try:
        conn = connect_readonly(path)
    except FileNotFoundError:
        return out
    except sqlite3.Error as exc:
        log.warning("event=transactions_not_recalled path=%s error=%r", path, str(exc))
        return out
    try:
        commands = conn.execute(_NEWEST, ("command", machine_id, 2 * window)).fetchall()
        ends = conn.execute(_NEWEST, ("completion", machine_id, window)).fetchall()
    except sqlite3.Error as exc:
        log.warning("event=transactions_not_recalled path=%s error=%r", path, str(exc))
        return out
    finally:
        conn.close()
    seen: set[str] = set()
    started: dict[str, float] = {}
    for when, details in commands:
        if len(seen) >= window:
            break
        made = _reply(details, when)
        if made is not None and made[0] not in seen:
            seen.add(made[0])
            started[made[0]] = when
            out.replies.append(made)
            out.since = when
    out.replies.reverse()
    for when, details in reversed(ends):
        notice = _notice(details, when, machine_id, started)
        if notice is not None:
            out.completions.append(notice)
    return out


_REPLY_CODES = frozenset(c.value for c in ReplyCode)
_ERROR_CODES = frozenset(c.value for c in ErrorCode)
_STATES = frozenset(s.value for s in MachineState)


def _reply(details: str, when: float) -> tuple[str, str, bytes] | None:
    """The reply a `command` event records, packed as the wire's msgpack (the transaction log
    keeps replies so, and decodes one only for a repeat); a repeat's row is skipped (its
    first one's counts). Plain JSON and set lookups: 4096 of them at every start."""
    try:
        event = json.loads(details)
        tid, command, code = event["transaction_id"], event["command"], event["code"]
        state, accepted = event.get("state"), event["accepted"]
    except (ValueError, KeyError, TypeError):
        return None  # a row of another version, or damaged: not guessed at
    if event.get("repeat") or not isinstance(tid, str) or not tid or not isinstance(command, str):
        return None
    if state is not None and state not in _STATES:
        return None
    reply: dict[str, Any] = {
        "schema_version": SCHEMA_VERSION,
        "transaction_id": tid,
        "command": command,
        "timecode": when,
        "request_timecode": None,
        "success": accepted is True,
        "state": state,
    }
    if accepted is True and code in _REPLY_CODES:
        reply.update(code=code, error=None, error_message="")
    elif accepted is False and code in _ERROR_CODES:
        message = str(event.get("message", ""))
        error = {"code": code, "message": message, "path": ""}
        reply.update(code=ReplyCode.RESP_ERROR.value, error=error, error_message=message)
    else:
        return None
    return tid, command, pack(reply)


def _notice(
    details: str, when: float, machine_id: str, started: dict[str, float]
) -> Completion | None:
    try:
        event = CompletionEvent.model_validate_json(details)
        if not event.transaction_id or event.command is None:
            return None
        return Completion(
            machine_id=machine_id,
            transaction_id=event.transaction_id,
            command=event.command,
            outcome=event.outcome,
            code=event.code,
            reason=event.reason,
            state=event.state,
            started_at=started.get(event.transaction_id, when),
            time=when,
        )
    except (ValidationError, ValueError):
        return None
