"""`machine credentials init DIR`: the dictionary and password files of the ACL profiles.

One `<user>.password` file per identity (one line, a random password) and `zenoh-users` (one
`user:password` line each): exactly what `MACHINE_ZENOH_DICTIONARY_FILE`,
`<SIDE>_ZENOH_PASSWORD_FILE` and the subjects of zenoh/acl.json5 expect (docs/security.md).
With `--station NAME …` each operator station gets a login of its own instead of the shared
`rider` one (its keys are `rider/<NAME>/…`, service/bus/stations.py).
"""

from __future__ import annotations

import secrets
from pathlib import Path

from schema.rider import login_ok
from service.core.atomic import atomic_write

IDENTITIES = ("machine", "rider", "monitor")
"""The ACL subjects of zenoh/acl.json5 and zenoh/tls.json5, by user name."""
ROLES = ("machine", "monitor")
"""Logins that are not operator stations."""
DICTIONARY = "zenoh-users"
PASSWORD_BYTES = 24
"""192 random bits per password (URL-safe base64, no ':' and no spaces)."""


def identities(stations: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The logins to make: the machine, one per station (`rider` without any), the monitor;
    ValueError names a station that cannot be a login."""
    for name in stations:
        if not login_ok(name) or name in ROLES:
            raise ValueError(
                f"station {name!r}: a login of letters, digits and ._@+- (at most 64), other than"
                f" {' and '.join(ROLES)}"
            )
    if len(set(stations)) != len(stations):
        raise ValueError("a station is named twice")
    return ("machine", *(stations or ("rider",)), "monitor")


class CredentialsExist(FileExistsError):
    """A file `init` would write exists already (pass force to replace it)."""


def password_file(directory: Path, user: str) -> Path:
    return directory / f"{user}.password"


def init_credentials(
    directory: Path, users: tuple[str, ...] = IDENTITIES, *, force: bool = False
) -> list[Path]:
    """Write fresh random credentials (files 0600, directory 0700); the paths written."""
    targets = [password_file(directory, u) for u in users] + [directory / DICTIONARY]
    existing = [p for p in targets if p.exists()]
    if existing and not force:
        names = ", ".join(str(p) for p in existing)
        raise CredentialsExist(
            f"{names}: exists already (--force replaces; every Rider needs the new file)"
        )
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    passwords = {u: secrets.token_urlsafe(PASSWORD_BYTES) for u in users}
    for user, password in passwords.items():
        _write_secret(password_file(directory, user), password + "\n")
    _write_secret(directory / DICTIONARY, "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    return targets


def _write_secret(path: Path, text: str) -> None:
    atomic_write(path, text.encode(), mode=0o600)
