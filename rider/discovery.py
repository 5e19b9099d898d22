"""Which machines are alive, once discovery has settled: the default-machine lookup.

A Rider that was not told which machine to use may only pick "the only machine alive" when it
has heard of them all. Just after a session opens it has not: a peer Rider learns of the other
peers by gossip and connects to them one by one, and their liveliness tokens arrive only then
(issue 22: a Rider connected to `fb` picked `fb` while `fa` was alive). So the lookup

1. follows `<prefix>/*/alive` (with history) and this session's links (`session.info`), and
   asks its neighbours for the tokens they hold (a liveliness query) whenever a link appears;
2. waits until it has a link, every such query has been answered, and nothing new has come
   for `settle` seconds (a new token or a new link restarts the wait);
3. reads who every node its queries reach is linked to (`@/<zid>/<whatami>`, the read-only
   admin space): a peer that such a node dialed (so it listens) but this session is not linked
   to yet means gossip has not finished: the wait goes on (step 2), up to `limit`;
4. looks past the edge of what it reached: a router that one of those nodes is linked to and
   this session did not reach (a peer does not forward our queries or its router's tokens to
   us, so the router's clients are out of sight) — and, for a client Rider, which gossip never
   links to peers, such a peer too — is asked directly, through a short client session
   (`probe`) to the address the node dialed it at: which machine tokens it knows (a router knows
   every machine of its site). So is a router this session reached that is linked to a peer
   this session is not linked to: a router passes no peer's tokens on to a peer session (zenoh
   1.x expects peers to link to each other), and gossip may not have linked us yet on a busy
   host, or never will (a peer that does not listen). One it cannot ask makes the lookup unsure
   (`Discovery.unseen`);
5. never settled within `limit` seconds: unsure too. The caller refuses (exit 4) when unsure.

Only `@/<zid>/<whatami>` is read from other nodes. zenoh 1.10's admin handlers for tokens,
link state and routes reply while holding the routing tables' lock and wedge the node when a
declaration comes in at that moment (eclipse-zenoh/zenoh#2619); this one does not.
"""

from __future__ import annotations

import contextlib
import json
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import zenoh

SETTLE_S = 0.15
"""Quiet time a read (`status`, `io`, …) waits after the last new token or link."""
MOTION_SETTLE_S = 0.3
"""Quiet time before a command (motion) without `--machine`: more certainty, more latency."""
LIMIT_S = 2.0
"""Discovery that has not settled after this long (two 1 s leases) is refused, not guessed."""
DISCOVERY_MIN_S = 1.0
"""The default-machine lookup waits at least this long, whatever is left of the timeout."""
ADMIN_TIMEOUT_S = 0.5
PROBE_TIMEOUT_S = 0.5
"""Bound on asking a router out of sight (open a client session, read its tokens)."""
POLL_S = 0.02
"""How often the links are looked at while waiting."""

Probe = Callable[[str], zenoh.Session]
"""Opens a short client session to one endpoint (the Rider's own config and credentials)."""


@dataclass
class Discovery:
    """What the lookup saw: machines alive, the links it had, and whether it settled."""

    alive: set[str] = field(default_factory=set)
    links: set[str] = field(default_factory=set)
    unlinked: set[str] = field(default_factory=set)
    """Listening peers a reached node is linked to that this session never linked to."""
    nodes_read: int = 0
    """Nodes whose links were read in step 3 (their admin space answered)."""
    probed: set[str] = field(default_factory=set)
    """Routers out of sight that were asked directly (their endpoints)."""
    unseen: list[str] = field(default_factory=list)
    """Routers out of sight that could not be asked: why, one line each."""
    settled: bool = False
    waited_s: float = 0.0

    @property
    def sure(self) -> bool:
        """Settled, and nothing on the network was out of sight."""
        return self.settled and not self.unseen

    def unsure(self) -> str:
        """Why a listing may miss a machine ("" when discovery is sure)."""
        if not self.links or self.sure:
            return ""
        if not self.settled:
            return f"discovery did not settle within {self.waited_s:.1f} s ({self.describe()})"
        return f"part of the network is out of sight ({self.describe()})"

    def describe(self) -> str:
        """One line for an error message: what was seen."""
        ids = ", ".join(sorted(self.alive)) or "none"
        text = f"machines seen: {ids}; links: {len(self.links)}"
        if self.unlinked:
            text += f"; peers not reached yet: {', '.join(sorted(self.unlinked))}"
        if self.unseen:
            text += f"; out of sight: {'; '.join(self.unseen)}"
        return text


T = TypeVar("T")


class Listing(list[T]):
    """What a lookup listed, and whether discovery had settled when it did (`complete`; when
    not, `note` says why): `Rider.machines()`."""

    def __init__(self, items: Iterable[T] = (), *, complete: bool = True, note: str = "") -> None:
        super().__init__(items)
        self.complete = complete
        self.note = note


@dataclass(frozen=True)
class _Router:
    """A router whose summary this session read: its peers, and where to ask it."""

    zid: str
    peers: frozenset[str]
    addresses: tuple[str, ...]
    """Where this session dialed it, then where it says it listens."""


@dataclass(frozen=True)
class _Neighbour:
    """A session some reached node has: who, what it is, and where that node dialed it."""

    zid: str
    whatami: str
    dialed: str | None
    """The endpoint the node connected to (the neighbour listens there); None if it was the
    neighbour that connected."""


def discover(
    session: zenoh.Session,
    prefix: str = "machine",
    *,
    settle: float = SETTLE_S,
    limit: float = LIMIT_S,
    probe: Probe | None = None,
    links_peers: bool = True,
    peer: bool = True,
) -> Discovery:
    """The machines alive on the network `session` is connected to, after discovery settled.
    `probe` asks nodes out of sight (step 4); without it they make the lookup unsure.
    `links_peers`: this session links to the peers gossip names (a peer with gossip on); a
    client does not, so a peer behind a node it reached is out of sight too. `peer`: this
    session is a peer, to which a router passes on no other peer's tokens."""
    changes: queue.Queue[_Change] = queue.Queue()

    def on_token(sample: zenoh.Sample) -> None:
        up = sample.kind == zenoh.SampleKind.PUT
        changes.put(_Change(str(sample.key_expr).split("/")[-2], up, asked=False))

    seen = Discovery()
    start = time.monotonic()
    own = str(session.zid())
    neighbours: list[_Neighbour] = []
    routers: list[_Router] = []
    reached: set[str] = set()
    sub: Any = session.liveliness().declare_subscriber(f"{prefix}/*/alive", on_token, history=True)
    try:
        while _quiet(session, prefix, changes, seen, settle, start + limit):
            neighbours, routers, answered = _neighbours(session)
            seen.nodes_read = len(answered)
            reached = seen.links | answered | {own}
            seen.unlinked = {
                n.zid
                for n in neighbours
                if links_peers and n.whatami == "peer" and n.dialed and n.zid not in reached
            }
            if not seen.unlinked:
                seen.settled = True
                break
    finally:
        sub.undeclare()
    if seen.settled:
        kinds = {"router"} if links_peers else {"router", "peer"}
        _probe_hidden(neighbours, kinds, reached, seen, prefix, probe)
        if peer:
            _probe_brokers(routers, reached, seen, prefix, probe)
    seen.waited_s = time.monotonic() - start
    return seen


class Lookahead:
    """A lookup begun early, on a thread of its own: the `rider` command starts one as soon as
    its session is open and loads the client and the wire models meanwhile, so the settle
    window runs while Python imports (rider/cli.py). `settle` is the quiet time it waits for;
    `result()` waits for it to end."""

    def __init__(self, settle: float, lookup: Callable[[float], Discovery]) -> None:
        self.settle = settle
        self._seen: Discovery | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run, args=(lookup,), name="rider-lookahead", daemon=True
        )
        self._thread.start()

    def _run(self, lookup: Callable[[float], Discovery]) -> None:
        try:
            self._seen = lookup(self.settle)
        except BaseException as exc:  # noqa: BLE001 - not swallowed: `result()` raises it
            self._error = exc

    def join(self) -> None:
        """Wait for the lookup to end (bounded by its limit), whatever it found."""
        self._thread.join()

    def result(self) -> Discovery:
        """What the lookup saw, once it ended (bounded by its limit); its error re-raised."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        assert self._seen is not None
        return self._seen


@dataclass(frozen=True)
class _Change:
    machine_id: str
    up: bool
    asked: bool
    """From a liveliness query (a snapshot) rather than the subscriber (live changes)."""


def _quiet(
    session: zenoh.Session,
    prefix: str,
    changes: queue.Queue[_Change],
    seen: Discovery,
    settle: float,
    deadline: float,
) -> bool:
    """Take tokens and links in until the session has a link, its liveliness queries are
    answered and nothing new came for `settle` s (True), or the deadline passed (False).
    Under load a peer's link can come after `zenoh.open` returned, and a neighbour's tokens
    later than `settle` after it: the query's end, not a quiet spell, says they are in."""
    last_change = time.monotonic()
    asking: list[threading.Event] = []
    gone: set[str] = set()
    while True:
        now = time.monotonic()
        links = _links(session)
        if links - seen.links:
            last_change = now
            asking.append(_ask_tokens(session, prefix, changes))
        seen.links |= links
        answered = all(done.is_set() for done in asking)
        if links and answered and now - last_change >= settle:
            return True
        if now >= deadline:
            return False
        try:
            change = changes.get(timeout=min(POLL_S, settle))
        except queue.Empty:
            continue
        while True:  # a burst of tokens is one change
            _apply(change, seen.alive, gone)
            try:
                change = changes.get_nowait()
            except queue.Empty:
                break
        last_change = time.monotonic()


def _apply(change: _Change, alive: set[str], gone: set[str]) -> None:
    """A snapshot's token never revives one the subscriber saw go away."""
    if change.asked:
        if change.machine_id not in gone:
            alive.add(change.machine_id)
    elif change.up:
        alive.add(change.machine_id)
        gone.discard(change.machine_id)
    else:
        alive.discard(change.machine_id)
        gone.add(change.machine_id)


def _ask_tokens(
    session: zenoh.Session, prefix: str, changes: queue.Queue[_Change]
) -> threading.Event:
    """A liveliness query to the neighbours; the event is set once it is answered."""
    done = threading.Event()

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            changes.put(_Change(str(reply.ok.key_expr).split("/")[-2], up=True, asked=True))

    try:
        handler = zenoh.handlers.Callback(on_reply, done.set)
        session.liveliness().get(f"{prefix}/*/alive", handler, timeout=ADMIN_TIMEOUT_S)
    except zenoh.ZError:
        done.set()
    return done


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


def _neighbours(session: zenoh.Session) -> tuple[list[_Neighbour], list[_Router], set[str]]:
    """The sessions of every peer or client node this session's queries reach (`@/*/*`: each
    node's own summary), the routers among those nodes, and the nodes that answered (queries
    and tokens are routed between us). A reached router's sessions are not neighbours: it
    routes its clients' tokens to us itself (its peers': `_probe_brokers`)."""
    found: list[_Neighbour] = []
    routers: dict[str, dict[str, Any]] = {}
    answered: set[str] = set()
    own = str(session.zid())
    dialed: dict[str, str] = {}
    for sample in _admin(session, "@/*/*"):
        with contextlib.suppress(ValueError, UnicodeDecodeError):
            info = json.loads(sample.payload.to_string())
            if isinstance(info, dict) and isinstance(info.get("sessions"), list):
                _, zid, whatami = str(sample.key_expr).split("/")[:3]
                answered.add(zid)
                if whatami == "router":
                    routers[zid] = info
                    continue
                sessions = _sessions(info)
                found += sessions
                if zid == own:
                    dialed = {n.zid: n.dialed for n in sessions if n.dialed}
    return found, [_router(z, info, dialed.get(z)) for z, info in routers.items()], answered


def _router(zid: str, info: dict[str, Any], dialed: str | None) -> _Router:
    """A router's summary; `dialed`: where this session connected to it, if it did."""
    peers = frozenset(n.zid for n in _sessions(info) if n.whatami == "peer")
    listens = [str(loc) for loc in info.get("locators") or []]
    return _Router(zid, peers, tuple(a for a in (dialed, *listens) if a))


def _sessions(info: dict[str, Any]) -> list[_Neighbour]:
    """One node's sessions. The node dialed a session when its own end of the link is not on
    a port it listens on (it is an ephemeral one)."""
    ports = {str(loc).rsplit(":", 1)[-1] for loc in info.get("locators") or []}
    out: list[_Neighbour] = []
    for s in info["sessions"]:
        if not isinstance(s, dict):
            continue
        dialed = [
            str(link.get("dst"))
            for link in s.get("links") or []
            if str(link.get("src")).rsplit(":", 1)[-1] not in ports
        ]
        out.append(
            _Neighbour(str(s.get("peer")), str(s.get("whatami")), dialed[0] if dialed else None)
        )
    return out


def _probe_hidden(
    neighbours: list[_Neighbour],
    kinds: set[str],
    reached: set[str],
    seen: Discovery,
    prefix: str,
    probe: Probe | None,
) -> None:
    """Step 4: ask each node a reached node is linked to, that this session did not reach."""
    hidden: dict[str, _Neighbour] = {}
    for n in neighbours:
        if n.whatami in kinds and n.zid not in reached and (n.zid not in hidden or n.dialed):
            hidden[n.zid] = n
    for zid, n in sorted(hidden.items()):
        if n.dialed is None:
            seen.unseen.append(f"{n.whatami} {zid} (it connected to a node this Rider reached)")
        else:
            _ask(f"{n.whatami} {zid} at {n.dialed}", n.dialed, "", seen, prefix, probe)


def _probe_brokers(
    routers: list[_Router], reached: set[str], seen: Discovery, prefix: str, probe: Probe | None
) -> None:
    """Step 4 for a router this session is linked to: a peer it is linked to that this session
    is not (gossip has not linked it yet, or it does not listen) holds tokens the router does
    not pass on to a peer session, so the router is asked as a client, where this session
    dialed it, else where it says it listens."""
    for router in routers:
        if router.zid not in seen.links or not router.peers - reached:
            continue
        if not router.addresses:
            seen.unseen.append(f"router {router.zid} (linked to peers; no address to ask it at)")
            continue
        at = router.addresses[0]
        _ask(f"router {router.zid} at {at}", at, " (linked to peers)", seen, prefix, probe)


def _ask(
    label: str, endpoint: str, unasked: str, seen: Discovery, prefix: str, probe: Probe | None
) -> None:
    """Ask the node at `endpoint` for its machine tokens (into `seen.alive`); one that could
    not be asked (`label`, and `unasked` when there was no probe) goes into `seen.unseen`."""
    if probe is None:
        seen.unseen.append(label + unasked)
    elif (ids := _probe_tokens(probe, endpoint, prefix)) is None:
        seen.unseen.append(f"{label} (did not answer)")
    else:
        seen.probed.add(endpoint)
        seen.alive |= ids


def _probe_tokens(probe: Probe, endpoint: str, prefix: str) -> set[str] | None:
    """The machine tokens a router knows, asked through a short client session; None if it
    could not be asked."""
    ids: set[str] = set()
    done = threading.Event()

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            ids.add(str(reply.ok.key_expr).split("/")[-2])

    try:
        with probe(endpoint) as session:
            handler = zenoh.handlers.Callback(on_reply, done.set)
            session.liveliness().get(f"{prefix}/*/alive", handler, timeout=PROBE_TIMEOUT_S)
            answered = done.wait(PROBE_TIMEOUT_S + 0.1)
    except zenoh.ZError:
        return None
    return set(ids) if answered else None
