"""`machine credentials init DIR`: the dictionary and password files of the ACL profiles.

One `<user>.password` file per identity (one line, a random password) and `zenoh-users` (one
`user:password` line each): exactly what `MACHINE_ZENOH_DICTIONARY_FILE`,
`<SIDE>_ZENOH_PASSWORD_FILE` and the subjects of zenoh/acl.json5 expect (docs/security.md).
Every operator station gets a login of its own (its keys are `rider/<NAME>/…`,
service/bus/stations.py): the stack's own two (`ui`, the compose file's UI and CLI, and
`gateway`, the plant gateway) and each named with `--stations bay1,bay2`. The login all
stations once shared, `rider`, only with `--shared-rider` (the daemon warns while it is used).
"""

from __future__ import annotations

import secrets
from collections.abc import Sequence
from pathlib import Path

from ride_machine.schema.rider import login_ok
from ride_machine.service.core.storage.atomic import NewFile, write_together

IDENTITIES = ("machine", "rider", "monitor")
"""One login per ACL subject of zenoh/acl.json5 and zenoh/tls.json5 (the shared `rider`)."""
ROLES = ("machine", "monitor", "router")
"""Logins that are not operator stations (the profiles name them in subjects of their own)."""
SHARED = "rider"
"""The login several stations shared before each had its own (`--shared-rider`)."""
STACK_STATIONS = ("ui", "gateway")
"""The stations of the shipped stack, always made: compose.yaml's Rider (its UI and CLI) and
the plant gateway (docker/compose.gateway.yaml)."""
DICTIONARY = "zenoh-users"
PASSWORD_BYTES = 24
"""192 random bits per password (URL-safe base64, no ':' and no spaces)."""
SECRET = 0o600


def identities(stations: tuple[str, ...] = (), *, shared: bool = False) -> tuple[str, ...]:
    """The logins to make: the machine, the stack's stations and `stations`, the shared `rider`
    when asked for, the monitor; ValueError names a station that cannot be a login."""
    for name in stations:
        if not login_ok(name) or name in (*ROLES, SHARED):
            raise ValueError(
                f"station {name!r}: a login of letters, digits and ._@+- (at most 64), other than"
                f" {', '.join(ROLES)} and {SHARED} (the shared login: --shared-rider)"
            )
    made = (*STACK_STATIONS, *stations)
    if len(set(made)) != len(made):
        raise ValueError(f"a station is named twice ({', '.join(STACK_STATIONS)} are always made)")
    return ("machine", *made, *((SHARED,) if shared else ()), "monitor")


class CredentialsExist(FileExistsError):
    """A file `init` would write exists already (pass force to replace it)."""


def password_file(directory: Path, user: str) -> Path:
    return directory / f"{user}.password"


def init_credentials(
    directory: Path,
    users: tuple[str, ...] = IDENTITIES,
    *,
    force: bool = False,
    also: Sequence[NewFile] = (),
) -> list[Path]:
    """Write fresh random credentials (files 0600, directory 0700), and the files of `also`,
    all together or none (`write_together`: a full disk leaves the older set whole); the
    paths written."""
    targets = [password_file(directory, u) for u in users] + [directory / DICTIONARY]
    existing = [p for p in targets if p.exists()]
    if existing and not force:
        names = ", ".join(str(p) for p in existing)
        raise CredentialsExist(
            f"{names}: exists already (--force replaces; every Rider needs the new file)"
        )
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    passwords = {u: secrets.token_urlsafe(PASSWORD_BYTES) for u in users}
    files = [
        NewFile(password_file(directory, user), f"{password}\n".encode(), SECRET)
        for user, password in passwords.items()
    ]
    dictionary = "".join(f"{u}:{p}\n" for u, p in passwords.items())
    files.append(NewFile(directory / DICTIONARY, dictionary.encode(), SECRET))
    written = [*files, *also]
    write_together(written)
    return [f.path for f in written]
