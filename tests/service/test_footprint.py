"""What the daemon's processes keep out of memory: OpenSSL's hash library (service/__init__.py),
more than a small SQLite page cache (service/adapters/eventdb.py), a large pipe buffer
(service/adapters/history_pipe.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

from ride_machine.schema.rider import digest
from ride_machine.service.adapters.eventdb import CACHE_KIB, connect
from ride_machine.service.adapters.history_pipe import (
    BATCH,
    FLUSH,
    MADE,
    READ_BYTES,
    encode,
    messages,
    write_all,
)
from tests.procs import REPO

_PROBE = """
import sys
import service
import service.adapters.history  # the daemon's side of the history, which brings pydantic
import secrets
from ride_machine.schema.rider import digest
maps = open("/proc/self/maps").read()
print(sys.modules["_hashlib"] is None, "libcrypto" in maps, digest(b"ride").hex(),
      len(secrets.token_urlsafe(16)))
"""


def test_the_daemons_modules_load_no_openssl_and_hash_as_before() -> None:
    out = subprocess.run(
        [sys.executable, "-c", _PROBE],
        check=False,
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    blocked, mapped, hashed, token = out.stdout.split()
    assert (blocked, mapped) == ("True", "False")
    assert hashed == digest(b"ride").hex()  # a Rider's confirmation digest, as this process has it
    assert token == "22"


def test_a_history_connection_caches_at_most_half_a_mebibyte(tmp_path: Path) -> None:
    conn = connect(tmp_path / "events.db")
    try:
        assert conn.execute("PRAGMA cache_size").fetchone() == (-CACHE_KIB,)
        assert CACHE_KIB <= 512  # SQLite's default, 2 MiB, stayed filled in the history process
    finally:
        conn.close()


def test_the_history_pipe_reads_messages_longer_than_its_buffer_whole() -> None:
    sent = [[BATCH, 0, [(MADE, "x", "d" * 300, 1.0, i) for i in range(2000)]], [FLUSH, 1, 0.5]]
    sent += [[BATCH, 0, [(MADE, "y", "e", 2.0, i)]] for i in range(500)]
    data = b"".join(encode(m) for m in sent)
    assert len(encode(sent[0])) > 4 * READ_BYTES  # one message longer than a read
    read_fd, write_fd = os.pipe()

    def write() -> None:
        with os.fdopen(write_fd, "wb", buffering=0) as out:
            write_all(out, data)

    writer = threading.Thread(target=write)
    writer.start()
    try:
        got = list(messages(read_fd))
    finally:
        writer.join(10)
        os.close(read_fd)
    assert got == [_as_read(m) for m in sent]


def _as_read(message: list[Any]) -> tuple[Any, ...]:
    """A message as `messages` gives it back: lists as tuples."""
    return tuple(_as_read(v) if isinstance(v, list | tuple) else v for v in message)
