"""Who may answer for a machine id: the session that holds it (pinned at first contact) and its
supervisor, never a second daemon with the same id (`DuplicateMachine`) nor a stranger
publishing under the machine's keys."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from .errors import DuplicateMachine
from .link import Link, bus_errors

KEY_CACHE = 256
"""Keys whose machine id a Rider remembers (the same few keys are asked again and again)."""

LOOK_AGAIN_S = 0.1
"""Before a reply is called a second daemon's, the holders are asked once more this long after
the look that did not name its replier: a liveliness query can come back short (one racing a
history replay, one on a loaded host; the project's CI once missed a live supervisor's token
and refused its reply), and `DuplicateMachine` tells an operator to stop a daemon."""


@dataclass
class Holders:
    """Who may answer for one machine id: its holder (pinned at first contact) and the
    supervisor that answers while the daemon is down."""

    holders: set[str] = dataclasses.field(default_factory=set)
    supervisors: set[str] = dataclasses.field(default_factory=set)
    pinned: str | None = None
    changes: int = 0
    """How many `update`s ran (counted after each, as a liveliness callback may run one on
    another thread while `Pinning.check_repliers` reads)."""
    allowed: zenoh.ZenohId | None = None
    """The replier (its `zenoh.ZenohId`) `Pinning.check_repliers` last allowed, valid while
    `changes` is still `allowed_at`: the next reply from it needs no second look."""
    allowed_at: int = -1

    def update(self, kind: str, zid: str, present: bool) -> None:
        group = self.holders if kind == "holder" else self.supervisors
        if present:
            group.add(zid)
        else:
            group.discard(zid)
        if self.pinned not in self.holders and len(self.holders) == 1:
            self.pinned = next(iter(self.holders))  # first contact, or the daemon restarted
        self.changes += 1

    def allows(self, zid: str) -> bool:
        if len(self.holders) > 1:
            return False
        return zid == self.pinned or zid in self.supervisors or self.pinned is None


class Pinning:
    """The holders this Rider knows per machine id, and the vetting of replies and samples."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.known: dict[str, Holders] = {}
        self._machine_of: dict[str, str | None] = {}
        """`machine_in`'s answers by key (bounded: cleared when it holds `KEY_CACHE` keys)."""
        self.pause: Callable[[float], None] = time.sleep
        """How the second look waits its `LOOK_AGAIN_S` (a test's hook)."""

    def machine_in(self, key: str) -> str | None:
        """The one machine id `key` is under (None: a wildcard id, or not a machine key)."""
        try:
            return self._machine_of[key]
        except KeyError:
            pass
        prefix = f"{self.link.key_prefix}/"
        mid: str | None = None
        if key.startswith(prefix):
            mid = key[len(prefix) :].split("/", 1)[0]
            if any(c in mid for c in "*$"):
                mid = None
        if len(self._machine_of) >= KEY_CACHE:
            self._machine_of.clear()
        self._machine_of[key] = mid
        return mid

    def holders(self, machine_id: str) -> Holders:
        """Ask who holds `machine_id` now (its `holder/<zid>` and `supervisor/<zid>` tokens)."""
        known = self.known.setdefault(machine_id, Holders())
        seen: dict[str, set[str]] = {"holder": set(), "supervisor": set()}
        base = f"{self.link.key_prefix}/{machine_id}"
        with bus_errors(f"cannot query the liveliness of {base}"):
            # One key per kind, not `*/*`: the ACL profiles allow exactly these.
            for kind, group in seen.items():
                for reply in self.link.session.liveliness().get(
                    f"{base}/{kind}/*", timeout=self.link.timeout
                ):
                    if reply.ok is not None:
                        group.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        for kind, group in (("holder", known.holders), ("supervisor", known.supervisors)):
            for zid in group - seen[kind]:
                known.update(kind, zid, False)
            for zid in seen[kind]:
                known.update(kind, zid, True)
        return known

    def _looked(self, machine_id: str, fine: Callable[[Holders], bool]) -> Holders:
        """`holders`, looked at a second time `LOOK_AGAIN_S` later when the first look is not
        `fine`: a look can come back short, and what follows is a `DuplicateMachine`."""
        known = self.holders(machine_id)
        if not fine(known):
            self.pause(LOOK_AGAIN_S)
            known = self.holders(machine_id)
        return known

    def check_repliers(self, key: str, replies: list[zenoh.Reply]) -> list[zenoh.Reply]:
        """One session answers for one machine, and it is the pinned one (or its supervisor);
        the replies to use (the daemon's, when its supervisor answered beside it)."""
        mid = self.machine_in(key)
        if mid is None:
            return replies
        if len(replies) == 1:  # a command's usual answer: one reply, one replier
            replier = replies[0].replier_id
            if replier is None:
                return replies
            replier_id = replier.zid
            known = self.known.get(mid)
            if (
                known is not None
                and known.allowed_at == known.changes
                and known.allowed == replier_id
            ):
                return replies  # the replier allowed last time, and nothing changed since
            self._vet(mid, key, str(replier_id), replier_id)
            return replies
        repliers = sorted({str(r.replier_id.zid) for r in replies if r.replier_id is not None})
        if len(repliers) > 1:
            replies, repliers = self._without_stand_in(mid, replies, repliers)
        if len(repliers) > 1:
            raise DuplicateMachine(mid, repliers, f"{len(repliers)} sessions replied to {key}")
        if repliers:
            self._vet(mid, key, repliers[0], None)
        return replies

    def _without_stand_in(
        self, mid: str, replies: list[zenoh.Reply], repliers: list[str]
    ) -> tuple[list[zenoh.Reply], list[str]]:
        """A supervisor answers for its machine while the daemon is down, and for a moment
        after a restarted daemon answers again (until it has seen the daemon's token): its
        reply is dropped when another session replied beside it. The look is `_looked`'s: the
        project's CI once saw a restarted daemon's status refused as a duplicate because a
        single look missed its supervisor's token, up all along."""
        known = self._looked(mid, lambda k: bool(k.supervisors.intersection(repliers)))
        others = [z for z in repliers if z not in known.supervisors]
        if not others or len(others) == len(repliers):
            return replies, repliers
        kept = [r for r in replies if r.replier_id is None or str(r.replier_id.zid) in others]
        return kept, others

    def _vet(self, mid: str, key: str, zid: str, replier_id: zenoh.ZenohId | None) -> None:
        """`zid`, the one session that replied to `key`, may answer for machine `mid`
        (`DuplicateMachine` otherwise); remembered by its `zenoh.ZenohId` when given."""
        known = self.known.get(mid)
        if known is None or not known.allows(zid):
            # first contact, or the holder changed since
            known = self._looked(mid, lambda k: k.allows(zid))
        checked = known.changes
        if len(known.holders) > 1:
            raise DuplicateMachine(mid, sorted(known.holders), "each holds the machine's token")
        if known.pinned is None and not known.holders:
            known.pinned = zid  # a daemon that names no holder: its first reply pins it
        if not known.allows(zid):
            raise DuplicateMachine(
                mid,
                [str(known.pinned), zid],
                f"{zid} replied to {key}, but this Rider talks to {known.pinned}"
                f" (holders seen: {', '.join(sorted(known.holders)) or 'none'}; supervisors"
                f" seen: {', '.join(sorted(known.supervisors)) or 'none'})",
            )
        if replier_id is not None:
            known.allowed, known.allowed_at = replier_id, checked

    def sample_ok(self, sample: zenoh.Sample) -> bool:
        """A publication under a machine from the pinned session (or its supervisor); one
        that names no source is not the machine's own (every machine publication names it)."""
        key = str(sample.key_expr)
        mid = self.machine_in(key)
        known = self.known.get(mid) if mid is not None else None
        if known is None or known.pinned is None:
            return True  # no contact yet: nothing to compare with
        source = sample.source_info
        if source is None:
            return False
        return known.allows(str(source.source_id.zid))
