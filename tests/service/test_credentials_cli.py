"""`machine credentials init` where it runs in the images (issue 57): in the machine's image,
which has no gateway libraries, and in a container, whose paths are not the user's."""

from __future__ import annotations

import errno
import sys
from pathlib import Path

import pytest

from ride_machine.service.adapters.credentials import DICTIONARY, identities, password_file
from ride_machine.service.adapters.opcua_credentials import opcua_files
from ride_machine.service.cli import EXIT_FAILED, main
from ride_machine.service.core.storage import atomic
from tests.procs import REPO, run_bounded

WITHOUT_CRYPTOGRAPHY = (
    "import sys; sys.path.insert(0, sys.argv.pop(1)); sys.modules['cryptography'] = None; "
    "from ride_machine.service.cli import main; sys.exit(main(sys.argv[1:]))"
)
"""`machine ARGS` in a Python that cannot import cryptography, as in the machine's image."""


def test_the_hints_name_the_directory_as_given(tmp_path: Path) -> None:
    """Reproduction 7: run in the image (`-w /site`), the hints named /site/secrets/…, a path
    of the container, not of the host where the files are."""
    done = run_bounded(
        [sys.executable, "-m", "ride_machine.service.cli", "credentials", "init", "secrets"],
        timeout=60.0, cwd=tmp_path, env={"PYTHONPATH": str(REPO)},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    hints = [line for line in done.stdout.splitlines() if not line.startswith("wrote ")]
    assert hints and not any(str(tmp_path) in line for line in hints), hints
    assert f"RIDER_ZENOH_PASSWORD_FILE={Path('secrets') / 'ui.password'}" in done.stdout


def test_without_the_gateway_libraries_the_logins_are_made_and_the_rest_said(
    tmp_path: Path,
) -> None:
    """The machine's image has no cryptography (the gateway's): the Zenoh logins are made, the
    OPC UA files are not, and the output says so (it failed with ModuleNotFoundError)."""
    secrets = tmp_path / "secrets"
    done = run_bounded(
        [sys.executable, "-c", WITHOUT_CRYPTOGRAPHY, str(REPO),
         "credentials", "init", str(secrets)],
        timeout=60.0, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert all(password_file(secrets, u).is_file() for u in identities())
    assert (secrets / DICTIONARY).is_file()
    assert not any(p.exists() for p in opcua_files(secrets))
    assert "its OPC UA files not made" in done.stdout


@pytest.mark.hazard("H38")
def test_a_full_disk_during_force_leaves_every_older_login_and_key_as_it_was(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`credentials init --force` writes a dozen files; a full disk after some of them left a
    mixed set: the dictionary old, some stations' passwords new, those stations locked out."""
    secrets = tmp_path / "secrets"
    assert main(["credentials", "init", str(secrets)]) == 0
    before = {p.name: p.read_bytes() for p in secrets.iterdir()}
    writes, real = [0], atomic.write_all

    def fills_up(fd: int, data: bytes) -> None:
        writes[0] += 1
        if writes[0] > 4:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(fd, data)

    monkeypatch.setattr(atomic, "write_all", fills_up)
    assert main(["credentials", "init", "--force", str(secrets)]) == EXIT_FAILED
    assert "No space left on device" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in secrets.iterdir()} == before  # no temp file either
    monkeypatch.setattr(atomic, "write_all", real)
    assert main(["credentials", "init", "--force", str(secrets)]) == 0
    after = {p.name: p.read_bytes() for p in secrets.iterdir()}
    assert after.keys() == before.keys()
    assert all(after[name] != before[name] for name in before)  # every file new, together
