"""Made at test time for the reliability suite: identities, certificates, secured and supervised
machines, and waits that end on Zenoh events (a status sample, a liveliness token)."""

from __future__ import annotations

import contextlib
import os
import queue
import secrets
import signal
import subprocess
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from ride_machine.common.credentials import MACHINE, RIDER, env_name
from ride_machine.rider.client import Rider
from ride_machine.schema.codec import Format, decode
from ride_machine.schema.commands import REST_STATES, Reply
from ride_machine.schema.status import FAULT_STATES, Status
from ride_machine.service.adapters.credentials import (
    DICTIONARY,
    IDENTITIES,
    init_credentials,
    password_file,
)
from tests.integration.support import STEP_TIMEOUT_S, write_fast_config
from tests.procs import (
    REPO,
    START_TIMEOUT_S,
    Daemon,
    children_running,
    free_port,
    machine_cmd,
    write_zenoh_config,
)

PROFILES = REPO / "zenoh"
ACL_PROFILE = PROFILES / "acl.json5"
TLS_PROFILE = PROFILES / "tls.json5"
USERS = IDENTITIES


# ---------------------------------------------------------------------------- identities
@dataclass(frozen=True)
class Identities:
    """A dictionary of random passwords, one password file per user, and a wrong one."""

    dictionary: Path
    password_files: Mapping[str, Path]
    wrong_password: Path

    def env(self, side: str, user: str, password_file: Path | None = None) -> dict[str, str]:
        """The `<SIDE>_ZENOH_USER/PASSWORD_FILE` variables for `user`."""
        pwd = password_file or self.password_files.get(user, self.wrong_password)
        return {env_name(side, "USER"): user, env_name(side, "PASSWORD_FILE"): str(pwd)}


def make_identities(directory: Path) -> Identities:
    """With `machine credentials init`'s own code, so every ACL test also checks its files."""
    init_credentials(directory, USERS)
    files = {user: password_file(directory, user) for user in USERS}
    wrong = _secret(directory / "wrong.password", secrets.token_urlsafe(18) + "\n")
    return Identities(directory / DICTIONARY, files, wrong)


def _secret(path: Path, text: str) -> Path:
    path.write_text(text)
    path.chmod(0o600)
    return path


# ---------------------------------------------------------------------------------- TLS
@dataclass(frozen=True)
class Tls:
    """A throw-away CA and a machine certificate it signed (for localhost and 127.0.0.1)."""

    ca: Path
    certificate: Path
    private_key: Path

    def machine_env(self) -> dict[str, str]:
        return {
            env_name(MACHINE, "TLS_CERTIFICATE"): str(self.certificate),
            env_name(MACHINE, "TLS_PRIVATE_KEY"): str(self.private_key),
        }

    def rider_env(self) -> dict[str, str]:
        return {env_name(RIDER, "TLS_ROOT_CA"): str(self.ca)}


def make_tls(directory: Path) -> Tls:
    """With the openssl CLI: nothing private is committed, everything is made here."""
    directory.mkdir(parents=True, exist_ok=True)
    ca_key, ca = directory / "ca.key", directory / "ca.crt"
    key, csr, cert = directory / "machine.key", directory / "machine.csr", directory / "machine.crt"
    ext = directory / "machine.ext"
    ext.write_text(
        "basicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature,keyEncipherment\n"
        "extendedKeyUsage=serverAuth,clientAuth\n"
        "subjectAltName=DNS:localhost,IP:127.0.0.1\n"
    )
    for cmd in (
        ["genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", ca_key],
        ["req", "-x509", "-new", "-key", ca_key, "-subj", "/CN=test ride CA", "-days", "2",
         "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=keyCertSign",
         "-out", ca],
        ["genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", key],
        ["req", "-new", "-key", key, "-subj", "/CN=localhost", "-out", csr],
        ["x509", "-req", "-in", csr, "-CA", ca, "-CAkey", ca_key, "-CAcreateserial",
         "-days", "2", "-extfile", ext, "-out", cert],
    ):  # fmt: skip
        subprocess.run(["openssl", *map(str, cmd)], check=True, capture_output=True, timeout=30)
    return Tls(ca, cert, key)


# ------------------------------------------------------------------------------ processes
@contextlib.contextmanager
def environ(values: Mapping[str, str | None]) -> Iterator[None]:
    """Set (None: unset) environment variables for the block; a Rider reads them when built."""
    saved = {k: os.environ.get(k) for k in values}
    for k, v in values.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


RIDER_VARIABLES = tuple(
    env_name(RIDER, item)
    for item in ("USER", "PASSWORD_FILE", "TLS_ROOT_CA", "TLS_CERTIFICATE", "TLS_PRIVATE_KEY")
)


def rider_as(daemon: Daemon, env: Mapping[str, str], **kwargs: object) -> Rider:
    """A Rider (not yet open) built with exactly these RIDER_ZENOH_* variables."""
    with environ({**dict.fromkeys(RIDER_VARIABLES), **env}):
        return daemon.rider(**kwargs)


def start_machine(  # noqa: PLR0913 - keyword-only test knobs
    tmp: Path,
    *,
    command: str = "run",
    profile: Path | None = None,
    scheme: str = "tcp",
    env: Mapping[str, str] | None = None,
    rider_env: Mapping[str, str] | None = None,
    machine_id: str = "m1",
    extra: list[str] | None = None,
    wait: bool = True,
) -> Daemon:
    """`machine run|supervise --sim` with a Zenoh profile, on a free loopback port.

    The returned `Daemon`'s zenoh config is a Rider's (peer, no access control): a Rider must
    never open its session with the machine's ACL profile, which would deny its own link.
    """
    endpoint = f"{scheme}/127.0.0.1:{free_port()}"
    data_dir = tmp / f"data-{machine_id}"
    rider_conf = write_zenoh_config(tmp)
    log_path = tmp / f"{command}-{machine_id}.log"
    cmd = machine_cmd(
        command,
        "--sim",
        "--id",
        machine_id,
        "--zenoh-config",
        str(profile or rider_conf),
        "--listen",
        endpoint,
        "--data-dir",
        str(data_dir),
        "--config",
        str(write_fast_config(tmp)),
        *(extra or []),
    )
    child_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    with log_path.open("w") as log:
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, text=True, cwd=REPO, env=child_env
        )
    daemon = Daemon(proc, endpoint, machine_id, data_dir, rider_conf, log_path, extra or [])
    if wait:
        try:
            wait_status(daemon, rider_env or {})
        except BaseException:
            daemon.stop(signal.SIGKILL)
            raise
    return daemon


def secured_machine(
    tmp: Path, ids: Identities, command: str, profile: Path, rider: str
) -> tuple[Daemon, dict[str, str]]:
    """`start_machine` on an ACL `profile` (`machine run`, or `supervise` with the daemon's own
    `machine` login), and the environment of a Rider process logged in as `rider`."""
    env = {env_name(MACHINE, "DICTIONARY_FILE"): str(ids.dictionary)}
    if command == "supervise":
        env.update(ids.env(MACHINE, "machine"))
    rider_env = ids.env(RIDER, rider)
    daemon = start_machine(tmp, command=command, profile=profile, env=env, rider_env=rider_env)
    child_env = {k: v for k, v in os.environ.items() if k not in RIDER_VARIABLES}
    return daemon, {**child_env, **rider_env}


def supervisor_child(daemon: Daemon) -> int:
    """The pid of the daemon child of a `machine supervise` process."""
    out = children_running(daemon.proc.pid, "ride_machine.service.cli")
    assert len(out) == 1, f"expected one daemon child of the supervisor, found {out}"
    return out[0]


# ---------------------------------------------------------------------------------- waits
class StatusFeed:
    """Every status sample published for the machine, decoded, in order (a subscription)."""

    def __init__(self, rider: Rider) -> None:
        self._q: queue.SimpleQueue[Status] = queue.SimpleQueue()
        self._sub: Any = rider.session.declare_subscriber(f"{rider.base}/status", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        fmt = Format.JSON if str(sample.encoding).startswith(Format.JSON) else Format.MSGPACK
        self._q.put(decode(Status, sample.payload.to_bytes(), fmt))

    def next(self, timeout: float = STEP_TIMEOUT_S) -> Status:
        try:
            return self._q.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"no status within {timeout:g} s") from None

    def until(self, pred: object, timeout: float = STEP_TIMEOUT_S) -> Status:
        """The first status for which `pred(status)` holds, within `timeout` in all (statuses
        that keep coming and never match, a heartbeat of a faulted machine, end it too)."""
        assert callable(pred)
        deadline = time.monotonic() + timeout
        last: Status | None = None
        while True:
            try:
                status = self._q.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                message = f"no matching status within {timeout:g} s; last {last}"
                raise AssertionError(message) from None
            if pred(status):
                return status
            last = status

    def close(self) -> None:
        self._sub.undeclare()


SETTLED = REST_STATES | FAULT_STATES
"""States a command's motion ends in."""


def settle(feed: StatusFeed, reply: Reply) -> Status:
    """The first status after `reply` (an accepted command) in a state its motion ends in."""
    assert reply.success, reply
    return feed.until(lambda s: s.time >= reply.timecode and s.state in SETTLED)


def wait_status(
    daemon: Daemon, rider_env: Mapping[str, str], timeout: float = START_TIMEOUT_S
) -> Status:
    """Block until the machine publishes a status (its scan loop runs and its bus is up).

    A status sample, not a query: a daemon's status queryable exists a moment before its first
    scan has produced anything to answer with.
    """
    with rider_as(daemon, rider_env, timeout=1.0) as r:
        feed = StatusFeed(r)
        try:
            for _ in range(int(timeout / 0.25)):
                try:
                    return feed.next(timeout=0.25)
                except AssertionError:
                    if daemon.proc.poll() is not None:
                        raise RuntimeError(
                            f"exited with {daemon.proc.returncode}:\n{daemon.log()}"
                        ) from None
            raise TimeoutError(f"no status within {timeout:g} s:\n{daemon.log()}")
        finally:
            feed.close()
