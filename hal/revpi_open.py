"""Opening revpimodio2 on a piCtory config and a process image, and what stops it: no config
found, an image that is absent, unusable or too short, revpimodio2 missing or refusing the file."""

from __future__ import annotations

import os
import stat
import warnings
from types import ModuleType
from typing import Any

from ride_machine.schema.findings import Finding, Severity

from .pictory import CONFIG_PATH, RevPiConfigError, error

KNOWN_CONFIGRSC = ("/etc/revpi/config.rsc", "/opt/KUNBUS/config.rsc")
"""Where piCtory saves its config on a device; searched when none is configured."""
PROCIMG_PATH = "/hal/revpi/procimg"
CONFIG_PROBLEMS = (KeyError, ValueError, TypeError, IndexError, AttributeError, RuntimeError)
"""What revpimodio2 raises on a config.rsc it cannot use."""


def raise_for_errors(findings: list[Finding]) -> None:
    """Raise `RevPiConfigError` with the error findings, if there are any."""
    errors = [f for f in findings if f.severity is Severity.ERROR]
    if errors:
        raise RevPiConfigError(errors)


def locate_configrsc(configrsc: str | None) -> str:
    """The config.rsc to use: the configured one, else the first piCtory location present."""
    if configrsc is not None:
        return configrsc
    for path in KNOWN_CONFIGRSC:
        if os.access(path, os.R_OK):
            return path
    raise RevPiConfigError(
        [
            error(
                "revpi_config",
                CONFIG_PATH,
                f"no piCtory config found at {' or '.join(KNOWN_CONFIGRSC)};"
                " set [hal.revpi] configrsc",
            )
        ]
    )


def procimg_findings(procimg: str, need_bytes: int | None) -> list[Finding]:
    """Problems with the process image: absent, not read/writable, or too short a file."""

    def bad(why: str) -> list[Finding]:
        return [error("revpi_procimg", PROCIMG_PATH, f"{procimg}: {why}")]

    try:
        st = os.stat(procimg)
    except OSError as exc:
        return bad(f"no process image there ({exc.strerror})")
    if not (stat.S_ISCHR(st.st_mode) or stat.S_ISREG(st.st_mode)):
        return bad("not a process image (neither the piControl device nor a file)")
    if not os.access(procimg, os.R_OK | os.W_OK):
        return bad("not readable and writable by this user")
    if need_bytes is not None and stat.S_ISREG(st.st_mode) and st.st_size < need_bytes:
        return bad(f"the file has {st.st_size} bytes; the piCtory config needs {need_bytes}")
    if need_bytes and stat.S_ISCHR(st.st_mode) and not _device_reaches(procimg, need_bytes):
        return bad(
            f"this device gives no data at byte {need_bytes - 1}, which the piCtory config"
            " needs: not the piControl device (e.g. /dev/null)?"
        )
    return []


def _device_reaches(procimg: str, need_bytes: int) -> bool:
    """Whether reading the device's byte `need_bytes - 1` gives data (seek and read, as
    revpimodio2 reads the image; nothing is written)."""
    try:
        fd = os.open(procimg, os.O_RDONLY)
    except OSError:
        return True  # permissions and the like are reported by the checks above, or at open
    try:
        os.lseek(fd, need_bytes - 1, os.SEEK_SET)
        return len(os.read(fd, 1)) == 1
    except OSError:
        return True  # a device that cannot be read this way: the open will tell
    finally:
        os.close(fd)


def import_revpimodio2() -> ModuleType:
    """revpimodio2, or a finding that says how to install it (it is an optional extra)."""
    try:
        import revpimodio2
    except ImportError as exc:
        raise RevPiConfigError(
            [
                Finding(
                    category="revpi_unavailable",
                    severity=Severity.ERROR,
                    path="/hal/backend",
                    message=f"the revpi backend needs revpimodio2 ({exc}); install it with"
                    " `pip install 'ride-machine[revpi]'`",
                )
            ]
        ) from exc
    module: ModuleType = revpimodio2
    return module


def open_modio(
    configrsc: str,
    procimg: str,
    *,
    simulator: bool = False,
    monitoring: bool = False,
) -> tuple[Any, list[Finding]]:
    """A `RevPiModIO` on these files, and its complaints about the config as warning findings.

    `configrsc` must already have passed `read_config`; anything revpimodio2 still rejects is
    turned into a `RevPiConfigError` instead of escaping as its own exception.
    """
    rp = import_revpimodio2()
    with warnings.catch_warnings(record=True) as caught:
        # Also contains revpimodio2's global `filterwarnings` call to this block.
        warnings.simplefilter("always")
        try:
            rpi = rp.RevPiModIO(
                autorefresh=False,
                monitoring=monitoring,
                syncoutputs=not monitoring,
                procimg=procimg,
                configrsc=configrsc,
                simulator=simulator,
                debug=False,
            )
        except OSError as exc:
            raise RevPiConfigError(
                [error("revpi_procimg", PROCIMG_PATH, f"cannot open {procimg}: {exc.strerror}")]
            ) from exc
        except CONFIG_PROBLEMS as exc:
            raise RevPiConfigError(
                [
                    error(
                        "revpi_config",
                        CONFIG_PATH,
                        f"revpimodio2 rejects {configrsc}: {type(exc).__name__} {exc}",
                    )
                ]
            ) from exc
    notes = [
        Finding(
            category="revpi_config",
            severity=Severity.WARNING,
            path=CONFIG_PATH,
            message=f"revpimodio2: {w.message}",
        )
        for w in caught
        if not issubclass(w.category, ResourceWarning)
    ]
    return rpi, notes
