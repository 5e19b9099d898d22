"""Which machines are alive, once discovery has settled: the default-machine lookup.

A Rider that was not told which machine to use may only pick "the only machine alive" when it
has heard of them all. Just after a session opens it has not: a peer Rider learns of the other
peers by gossip and connects to them one by one, and their liveliness tokens arrive only then
(issue 22: a Rider connected to `fb` picked `fb` while `fa` was alive). So the lookup

1. follows `<prefix>/*/alive` (with history) and this session's links (`session.info`);
2. waits until nothing new has come for `settle` seconds (a new token, a new link, a peer
   named by gossip that this session is not linked to yet all restart the wait);
3. then asks every node it is linked to (its own admin space too) which machine tokens *they*
   know (`@/<zid>/<whatami>/token/<prefix>/*/alive`): a router knows every machine on the site,
   a peer daemon knows the peers it is linked to, so a machine this session has not reached
   yet is still counted;
4. gives up after `limit` seconds if it never settles: the caller refuses (exit 4).
"""

from __future__ import annotations

import queue
import re
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import zenoh

SETTLE_S = 0.15
"""Quiet time a read (`status`, `io`, …) waits after the last new token or link."""
MOTION_SETTLE_S = 0.3
"""Quiet time before a command (motion) without `--machine`: more certainty, more latency."""
LIMIT_S = 2.0
"""Discovery that has not settled after this long (two 1 s leases) is refused, not guessed."""
ADMIN_TIMEOUT_S = 0.5
POLL_S = 0.02
"""How often the links and the gossip graph are looked at while waiting."""
_NODE = re.compile(r'label = "([0-9a-f]+)"')


@dataclass
class Discovery:
    """What the lookup saw: machines alive, the links it had, and whether it settled."""

    alive: set[str] = field(default_factory=set)
    links: set[str] = field(default_factory=set)
    unlinked: set[str] = field(default_factory=set)
    """Peers named by gossip that this session never linked to."""
    neighbours_asked: int = 0
    """Nodes (this session included) whose admin space named a machine token in step 3."""
    settled: bool = False
    waited_s: float = 0.0

    def describe(self) -> str:
        """One line for an error message: what was seen."""
        ids = ", ".join(sorted(self.alive)) or "none"
        text = f"machines seen: {ids}; links: {len(self.links)}"
        if self.unlinked:
            text += f"; peers not reached yet: {', '.join(sorted(self.unlinked))}"
        return text


def discover(
    session: zenoh.Session,
    prefix: str = "machine",
    *,
    settle: float = SETTLE_S,
    limit: float = LIMIT_S,
) -> Discovery:
    """The machines alive on the network `session` is connected to, after discovery settled."""
    changes: queue.Queue[tuple[str, bool]] = queue.Queue()

    def on_token(sample: zenoh.Sample) -> None:
        changes.put((str(sample.key_expr).split("/")[-2], sample.kind == zenoh.SampleKind.PUT))

    seen = Discovery()
    start = time.monotonic()
    last_change = start
    sub: Any = session.liveliness().declare_subscriber(f"{prefix}/*/alive", on_token, history=True)
    try:
        while True:
            now = time.monotonic()
            links = _links(session)
            unlinked = _gossiped(session) - links - {str(session.zid())}
            if links - seen.links or unlinked:
                last_change = now
            seen.links |= links
            seen.unlinked = unlinked
            if now - last_change >= settle:
                seen.settled = True
                break
            if now - start >= limit:
                break
            try:
                mid, up = changes.get(timeout=min(POLL_S, settle))
            except queue.Empty:
                continue
            while True:  # a burst of tokens is one change
                if up:
                    seen.alive.add(mid)
                else:
                    seen.alive.discard(mid)
                try:
                    mid, up = changes.get_nowait()
                except queue.Empty:
                    break
            last_change = time.monotonic()
    finally:
        sub.undeclare()
    if seen.settled:
        asked, known = _neighbour_tokens(session, prefix)
        seen.neighbours_asked = asked
        seen.alive |= known
    seen.waited_s = time.monotonic() - start
    return seen


def _links(session: zenoh.Session) -> set[str]:
    info = session.info
    return {str(z) for z in info.peers_zid()} | {str(z) for z in info.routers_zid()}


def _admin(session: zenoh.Session, key: str) -> list[zenoh.Sample]:
    """Replies to an admin-space query, within our own bound: an admin query to a node that is
    going away was seen to outlive its Zenoh timeout, so the replies come through a callback."""
    got: list[zenoh.Sample] = []
    done = threading.Event()

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            got.append(reply.ok)

    try:
        session.get(key, zenoh.handlers.Callback(on_reply, done.set), timeout=ADMIN_TIMEOUT_S)
    except zenoh.ZError:
        return []  # the admin space is off or denied: the settle window alone decides
    done.wait(ADMIN_TIMEOUT_S + 0.1)
    return list(got)


def _gossiped(session: zenoh.Session) -> set[str]:
    """Nodes this session's own link-state graph names (peers gossip told it about)."""
    nodes: set[str] = set()
    for sample in _admin(session, f"@/{session.zid()}/*/linkstate/**"):
        nodes |= set(_NODE.findall(sample.payload.to_string()))
    return nodes


def _neighbour_tokens(session: zenoh.Session, prefix: str) -> tuple[int, set[str]]:
    """Machine tokens known to this session and to every node it is linked to."""
    ids: set[str] = set()
    asked: set[str] = set()
    for sample in _admin(session, f"@/*/*/token/{prefix}/*/alive"):
        parts = str(sample.key_expr).split("/")
        asked.add(parts[1])
        ids.add(parts[-2])
    return len(asked), ids
