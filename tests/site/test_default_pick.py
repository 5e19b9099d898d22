"""The default-machine pick never names "the only machine" while another one is alive (issue 22).

The trial test: a router, a real daemon `a` (a peer linked to the router) and a second machine
`b` that appears and disappears at random moments (tests/site/appearer.py, its own process: a
fresh Zenoh session each time, alternately a peer that listens on its own port and links to
`a` and the router, and a client of the router). Worker threads in this process make fresh
Rider sessions, connecting to each endpoint in turn (a's port and b's port as a peer, the
router as a client and as a peer), and look up the default machine, reads and command-grade
lookups alternately. A trial is wrong if it picked `a` while `b` was alive from before the
Rider opened until after it answered (or `b` while `b` was gone throughout). `PICK_TRIALS`
sets the count (default 1000), `PICK_WORKERS` the threads, `PICK_DUMP` a file for every trial.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from ride_machine.rider.client import AmbiguousMachine, NoMachine, Rider, UnsureMachine
from tests.procs import REPO, START_TIMEOUT_S, free_port, start_daemon, stop_process
from tests.site.stand import (
    PEER_CONFIG,
    Lines,
    Router,
    Site,
    run_cli,
    site,
    wait_tokens,
    write_doc_config,
)

TRIALS = int(os.environ.get("PICK_TRIALS", "1000"))
WORKERS = int(os.environ.get("PICK_WORKERS", "12"))
TRIALS_MAX_S = 600.0
"""Bound on the whole trial run (every thread, and the appearer's life)."""
ISSUE_TRIES = 24
PHASE = 50
B_UP_S = (0.3, 2.5)
B_DOWN_S = (0.2, 1.2)
"""How long `b` stays up and away (uniform between the two): longer than a lookup takes, so
many trials meet it alive throughout."""
B_CYCLE_S = sum(B_UP_S) / 2 + sum(B_DOWN_S) / 2
"""`b`'s mean appearance and absence (its session's opening and closing come on top)."""
B_AWAY_MAX_S = B_UP_S[1] + 2 * B_DOWN_S[1] + 3.0
"""The longest b's port can be silent: away, a client's appearance, away again, and a loaded
host's session opening on top."""


@dataclass(frozen=True)
class Trial:
    kind: str
    motion: bool
    start: float
    end: float
    lookup_s: float
    outcome: str  # a machine id, "several", "unsure", "none", "unreachable" or "error …"
    zid: str = ""
    """The Rider session's id (names it in another lookup's "out of sight" list)."""
    seen: str = ""
    """What its discovery saw (`rider.discovery.Discovery`): a "none" is told by it."""


@pytest.fixture(scope="module")
def stand(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    with site(tmp_path_factory.mktemp("pick")) as s:
        s.start_daemons({"a": "peer"})
        yield s


def look_up(kind: str, endpoint: str, config: Path, motion: bool = False) -> Trial:
    """One fresh Rider session and one default-machine lookup; `start`/`end` in wall time
    (the appearer's clock) around the whole session."""
    lookup_s = 0.0
    seen = ""
    if kind == "peer@b" and not listening(endpoint, B_AWAY_MAX_S):  # b away, or a client
        return Trial(kind, motion, time.time(), time.time(), lookup_s, "unreachable")
    start = time.time()
    r = Rider(None, connect=[endpoint], zenoh_config_path=config, timeout=2.0).open()
    try:
        t0 = time.monotonic()
        try:
            outcome = r.resolve_machine(motion=motion)
        except UnsureMachine as exc:
            outcome = f"unsure {exc}"
        except AmbiguousMachine:
            outcome = "several"
        except NoMachine:
            outcome = "none"
        lookup_s = time.monotonic() - t0
        seen = repr(r.discovery)
    except Exception as exc:  # noqa: BLE001 - a trial that breaks is reported, never hidden
        outcome = f"error {exc!r}"
    finally:
        r.close()
    return Trial(kind, motion, start, time.time(), lookup_s, outcome, r.rider_id, seen)


def listening(endpoint: str, wait_s: float) -> bool:
    """Something accepts TCP connections at `tcp/HOST:PORT`, asked until it does (bounded by
    `wait_s`): no Zenoh session is opened for an empty port (no retrying session that links
    once b comes up). A peer@b trial waits for b's next peer appearance: one that took "no"
    for an answer at once let a whole phase of them pass while b was away or a client (run 85,
    under load: 244 of 250 unreachable, none met b alive)."""
    host, _, port = endpoint.removeprefix("tcp/").rpartition(":")
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with socket.create_connection((host, int(port)), timeout=0.2):
                return True
        except OSError:
            if time.monotonic() > deadline:
                return False
        time.sleep(0.05)  # bounded poll of another process's port, not a settle


def b_intervals(lines: list[str]) -> list[tuple[float, float]]:
    """When `b` was alive: (token declared, token undeclared) pairs from the appearer."""
    out: list[tuple[float, float]] = []
    up: float | None = None
    for line in lines:
        event = json.loads(line)
        if "up" in event:
            up = event["up"]
        elif "down" in event and up is not None:
            out.append((up, event["down"]))
            up = None
    if up is not None:
        out.append((up, float("inf")))
    return out


def quantile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(len(ordered) * q))] if ordered else float("nan")


def start_appearer(stand: Site, b_port: int) -> subprocess.Popen[str]:
    """Machine `b` appearing and going on its cadence (tests/site/appearer.py), beside `a`."""
    a = stand.daemons["a"]
    return subprocess.Popen(
        [
            *[sys.executable, "-m", "tests.site.appearer", "--id", "b"],
            *["--peer-config", str(PEER_CONFIG), "--client-config", str(stand.client_config)],
            *["--listen", f"tcp/127.0.0.1:{b_port}", "--connect", a.endpoint],
            *["--router", stand.router.endpoint, "--for", str(TRIALS_MAX_S)],
            *["--up", *map(str, B_UP_S), "--down", *map(str, B_DOWN_S)],
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=REPO,
    )


def run_trials(ends: dict[str, tuple[str, Path]]) -> list[Trial]:
    """`TRIALS` lookups by `WORKERS` threads, endpoint by endpoint, within `TRIALS_MAX_S`."""
    kinds = list(ends)
    trials: list[Trial] = []
    lock = threading.Lock()
    counter = iter(range(TRIALS))
    deadline = time.monotonic() + TRIALS_MAX_S

    def worker() -> None:
        for n in counter:
            if time.monotonic() > deadline:
                return
            # one endpoint at a time (phases of PHASE trials): peer Riders on a daemon's port are
            # out of a client Rider's sight, so mixing them would make client lookups unsure
            kind = kinds[n // PHASE % len(kinds)]
            trial = look_up(kind, *ends[kind], motion=bool(n % 2))
            with lock:
                trials.append(trial)

    threads = [threading.Thread(target=worker, daemon=True) for _ in range(WORKERS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(max(0.0, deadline - time.monotonic()))
    return trials


def report(
    summary: dict[str, object], trials: list[Trial], timeline: object, appearances: object
) -> None:
    """Print the trials' summary with their outcomes and lookup times; dump everything to the
    file `PICK_DUMP` names, when it does."""
    summary["unsure"] = sum(1 for t in trials if t.outcome.startswith("unsure"))
    summary["outcomes"] = dict(Counter(t.outcome.split()[0] for t in trials))
    for motion, name in ((False, "read"), (True, "command")):
        times = [t.lookup_s for t in trials if t.motion is motion and t.outcome in ("a", "several")]
        summary[f"{name}_lookup_s"] = {
            "p50": round(quantile(times, 0.5), 3),
            "p90": round(quantile(times, 0.9), 3),
        }
    print(f"\ndefault-pick {json.dumps(summary)}")
    if os.environ.get("PICK_DUMP"):
        dump = {
            "summary": summary,
            "timeline": timeline,
            "appearer": appearances,
            "trials": [t.__dict__ for t in trials],
        }
        Path(os.environ["PICK_DUMP"]).write_text(json.dumps(dump, default=str))


@pytest.mark.hazard("H37")
@pytest.mark.integration
def test_default_pick_trials_never_pick_while_another_machine_is_alive(stand: Site) -> None:
    a = stand.daemons["a"]
    b_port = free_port()
    ends = {
        "peer@a": (a.endpoint, PEER_CONFIG),
        "peer@b": (f"tcp/127.0.0.1:{b_port}", PEER_CONFIG),
        "client@router": (stand.router.endpoint, stand.client_config),
        "peer@router": (stand.router.endpoint, PEER_CONFIG),
    }
    kinds = list(ends)
    appearer = start_appearer(stand, b_port)
    lines = Lines(appearer)
    try:
        lines.wait_for('"up"')
        began = time.monotonic()
        trials = run_trials(ends)
        took = time.monotonic() - began
    finally:
        stop_process(appearer)
    appearances = [*lines.seen, *lines.rest()]
    timeline = b_intervals(appearances)

    def b_alive_throughout(t: Trial) -> bool:
        return any(up <= t.start and t.end <= down for up, down in timeline)

    def b_gone_throughout(t: Trial) -> bool:
        return all(down <= t.start or t.end <= up for up, down in timeline)

    wrong = [
        t
        for t in trials
        if (t.outcome == "a" and b_alive_throughout(t))
        or (t.outcome == "b" and b_gone_throughout(t))
        or t.outcome.split()[0] not in ("a", "b", "several", "unsure", "none", "unreachable")
        or (t.outcome == "unreachable" and t.kind != "peer@b")
    ]
    # `a` is up throughout and reachable from every endpoint but b's (nothing listens there
    # while b is away): "no machine" from those would be a lookup that broke
    missed_a = [t for t in trials if t.outcome == "none" and t.kind != "peer@b"]
    caught = {k: sum(1 for t in trials if t.kind == k and b_alive_throughout(t)) for k in kinds}
    summary = {
        "trials": len(trials),
        "workers": WORKERS,
        "took_s": round(took, 1),
        "b_appearances": len(timeline),
        "b_alive_throughout": sum(caught.values()),
        "b_alive_by_endpoint": caught,
        "b_gone_throughout": sum(map(b_gone_throughout, trials)),
        "wrong": len(wrong),
    }
    report(summary, trials, timeline, appearances)
    assert len(trials) == TRIALS, f"only {len(trials)} trials in {TRIALS_MAX_S:g} s"
    # Half of what b's cadence gives over the trials' time: faster lookups race fewer of them.
    assert len(timeline) >= took / B_CYCLE_S / 2, "b hardly appeared: the trials raced nothing"
    assert all(caught.values()), f"some endpoint never met b alive: {caught}"
    assert wrong == [], wrong[:10]
    assert missed_a == [], missed_a[:10]


@pytest.mark.integration
def test_a_peer_rider_at_the_router_sees_a_peer_machine_it_is_not_linked_to(
    stand: Site, tmp_path: Path
) -> None:
    """Run 17's "no machine" while `a` was up: a router passes a peer machine's token on to no
    peer session (zenoh 1.x leaves peers to link to each other), and on a busy host gossip had
    not linked the Rider to `a` when discovery settled. With gossip off it never does: the
    lookup asks the router as a client and finds `a`, every time."""
    text = PEER_CONFIG.read_text()
    assert "gossip: { enabled: true }" in text
    no_gossip = tmp_path / "no-gossip.json5"
    no_gossip.write_text(text.replace("gossip: { enabled: true }", "gossip: { enabled: false }"))
    router = stand.router.endpoint
    outcomes = [look_up("peer@router", router, no_gossip).outcome for _ in range(ISSUE_TRIES // 4)]
    assert outcomes == ["a"] * (ISSUE_TRIES // 4), outcomes


@pytest.mark.hazard("H37")
@pytest.mark.integration
def test_issue_22_two_peer_daemons_the_rider_never_picks_the_one_it_connected_to(
    tmp_path: Path,
) -> None:
    """fa listens; fb listens and links to fa; Riders connect to fb (and to fa): every default
    lookup sees both and refuses (exit 4's AmbiguousMachine), none picks the one it reached."""
    zconf = ["--zenoh-config", str(PEER_CONFIG)]
    fa = start_daemon(tmp_path, "fa", extra=zconf)
    try:
        fb = start_daemon(tmp_path, "fb", extra=[*zconf, "--connect", fa.endpoint])
        try:
            outcomes = []
            for n in range(ISSUE_TRIES):
                endpoint = (fb.endpoint, fa.endpoint)[n % 2]
                outcomes.append(look_up("issue", endpoint, PEER_CONFIG).outcome)
        finally:
            fb.stop()
    finally:
        fa.stop()
    assert outcomes == ["several"] * ISSUE_TRIES, outcomes


def rider_cli(endpoint: str, *args: str) -> subprocess.CompletedProcess[str]:
    """`rider --connect ENDPOINT --zenoh-config zenoh.json5 ARGS` (a peer Rider), bounded."""
    cmd = [sys.executable, "-m", "ride_machine.rider.cli", "--connect", endpoint]
    return run_cli([*cmd, "--zenoh-config", str(PEER_CONFIG), *args])


@pytest.mark.integration
def test_through_a_peer_daemons_port_a_client_of_its_router_is_seen(tmp_path: Path) -> None:
    """The last wrong pick of the first lookup: `a` a peer linked to the router, `b` a client
    of the router, a Rider on a's port. `a` passes on neither b's token nor our queries; the
    lookup reads a's summary and asks the router behind it, so every lookup sees both."""
    with site(tmp_path) as stand:
        stand.start_daemons({"a": "peer", "b": "client"})
        a = stand.daemons["a"]
        outcomes = [
            look_up("peer@a", a.endpoint, PEER_CONFIG, motion=bool(n % 2)).outcome
            for n in range(ISSUE_TRIES // 4)
        ]
        cli = rider_cli(a.endpoint, "status")
    assert outcomes == ["several"] * (ISSUE_TRIES // 4), outcomes
    assert cli.returncode == 4, cli
    assert "several machines are alive (a, b)" in cli.stderr


@pytest.mark.hazard("H37")
@pytest.mark.integration
def test_a_router_that_dialed_the_machine_is_out_of_sight_so_the_pick_is_unsure(
    tmp_path: Path,
) -> None:
    """A router that connected to `a` itself (as the compose router profile does) left no
    address this Rider could ask it at: without `--machine` it refuses (exit 4) and says what is
    out of sight; with `--machine a` it answers."""
    a = start_daemon(tmp_path, "a", extra=["--zenoh-config", str(PEER_CONFIG)])
    router = Router(write_doc_config(tmp_path, "router"), tmp_path, connect=[a.endpoint])
    client = write_doc_config(tmp_path, "client")
    try:
        router.start()
        # the router has dialed a once a's token is seen through it
        with Rider(None, connect=[router.endpoint], zenoh_config_path=client) as through:
            wait_tokens(through.follow_machines(timeout=0.2), {"a": True}, START_TIMEOUT_S)
        with (
            Rider(None, connect=[a.endpoint], zenoh_config_path=PEER_CONFIG) as r,
            pytest.raises(UnsureMachine, match="out of sight: router") as refused,
        ):
            r.resolve_machine()
        unsure = rider_cli(a.endpoint, "status")
        named = rider_cli(a.endpoint, "--machine", "a", "status")
    finally:
        router.kill(signal.SIGTERM)
        a.stop()
    assert "connect where it can be seen, or pass --machine ID" in str(refused.value)
    assert unsure.returncode == 4, unsure
    assert "part of the network is out of sight" in unsure.stderr
    assert named.returncode == 0, named


@pytest.mark.integration
def test_a_client_rider_cannot_see_a_machine_linked_only_to_a_peer_daemon(tmp_path: Path) -> None:
    """`b` a peer linked only to `a` (a peer linked to the router): the router never hears of
    b, so a client of the router refuses as unsure (it picked `a` before); a peer Rider on the
    router is linked to both by gossip and sees several."""
    with site(tmp_path) as stand:
        stand.start_daemons({"a": "peer"})
        a = stand.daemons["a"]
        b = start_daemon(
            tmp_path, "b", extra=["--zenoh-config", str(PEER_CONFIG), "--connect", a.endpoint]
        )
        try:
            client = look_up("client@router", stand.router.endpoint, stand.client_config).outcome
            peer = look_up("peer@router", stand.router.endpoint, PEER_CONFIG).outcome
        finally:
            b.stop()
    assert client.startswith("unsure part of the network is out of sight"), client
    assert "out of sight: peer" in client
    assert peer == "several", peer
