"""What the daemon's processes keep out of memory: OpenSSL's hash library (service/__init__.py),
and more than a small SQLite page cache (service/adapters/eventdb.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from schema.rider import digest
from service.adapters.eventdb import CACHE_KIB, connect
from tests.procs import REPO

_PROBE = """
import sys
import service
import service.adapters.history  # the history process's module, which brings pydantic
import secrets
from schema.rider import digest
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
