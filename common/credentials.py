"""Zenoh credentials from the environment: the contract both sides follow (no zenoh import here).

A side (`MACHINE` or `RIDER`) names its secrets with environment variables that point at files,
so nothing secret is baked into an image or a config file:

- `<SIDE>_ZENOH_USER` + `<SIDE>_ZENOH_PASSWORD_FILE`: this side's user/password identity;
- `<SIDE>_ZENOH_DICTIONARY_FILE`: the `user:password` lines this side accepts (a listener);
- `<SIDE>_ZENOH_TLS_ROOT_CA`, `<SIDE>_ZENOH_TLS_CERTIFICATE`, `<SIDE>_ZENOH_TLS_PRIVATE_KEY`:
  PEM files for `tls/` links (the certificate and key serve listening and, with mTLS, connecting).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path

MACHINE = "MACHINE"
RIDER = "RIDER"

_USRPWD = "transport/auth/usrpwd"
_TLS = "transport/link/tls"
_TLS_FILES = {
    "TLS_ROOT_CA": [f"{_TLS}/root_ca_certificate"],
    "TLS_CERTIFICATE": [f"{_TLS}/listen_certificate", f"{_TLS}/connect_certificate"],
    "TLS_PRIVATE_KEY": [f"{_TLS}/listen_private_key", f"{_TLS}/connect_private_key"],
}


class CredentialError(ValueError):
    """A credential variable is incomplete or points at a file that cannot be used."""


def env_name(side: str, item: str) -> str:
    """`MACHINE_ZENOH_USER` and friends."""
    return f"{side}_ZENOH_{item}"


def zenoh_settings(side: str, env: Mapping[str, str] | None = None) -> dict[str, str]:
    """Zenoh config paths → JSON values for the credentials `side`'s environment names.

    Empty when none are set; raises `CredentialError` with the variable to fix otherwise.
    """
    env = os.environ if env is None else env
    out: dict[str, str] = {}
    user_var, pwd_var = env_name(side, "USER"), env_name(side, "PASSWORD_FILE")
    user, pwd_file = env.get(user_var, ""), env.get(pwd_var, "")
    if user or pwd_file:
        if not (user and pwd_file):
            missing = pwd_var if user else user_var
            raise CredentialError(f"{user_var} and {pwd_var} go together; {missing} is not set")
        if ":" in user or user != user.strip():
            raise CredentialError(f"{user_var}: a user name has no ':' and no outer spaces")
        out[f"{_USRPWD}/user"] = json.dumps(user)
        out[f"{_USRPWD}/password"] = json.dumps(_password(pwd_var, pwd_file))
    dict_var = env_name(side, "DICTIONARY_FILE")
    if env.get(dict_var):
        out[f"{_USRPWD}/dictionary_file"] = json.dumps(_readable(dict_var, env[dict_var]))
    for item, paths in _TLS_FILES.items():
        var = env_name(side, item)
        if env.get(var):
            value = json.dumps(_readable(var, env[var]))
            out.update(dict.fromkeys(paths, value))
    return out


def login(side: str, env: Mapping[str, str] | None = None) -> str | None:
    """The user name `side` logs in with (`<SIDE>_ZENOH_USER`), None without one."""
    env = os.environ if env is None else env
    return env.get(env_name(side, "USER")) or None


def _readable(var: str, path: str) -> str:
    """The absolute path, after checking it can be read (Zenoh's own error names no variable)."""
    p = Path(path)
    try:
        with p.open("rb"):
            pass
    except OSError as exc:
        raise CredentialError(f"{var}={path}: cannot read it ({exc.strerror})") from exc
    return str(p.resolve())


def _password(var: str, path: str) -> str:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise CredentialError(f"{var}={path}: cannot read it ({exc.strerror})") from exc
    except UnicodeDecodeError as exc:
        raise CredentialError(f"{var}={path}: not UTF-8 text") from exc
    # Zenoh trims dictionary entries too, so outer whitespace can never be part of a password.
    password = text.strip()
    if not password or "\n" in password:
        raise CredentialError(f"{var}={path}: the file must hold one non-empty line")
    return password
