"""The child's config files: written whole or not at all, owner-only."""

from __future__ import annotations

import errno
import os
from pathlib import Path

import pytest

from ride_machine.service.supervision.toml_out import write_private


def test_a_write_that_fails_leaves_the_older_file_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "machine.toml"
    write_private(path, 'data_dir = "/data"\n')
    real_open = os.open

    def full_disk(file: str | os.PathLike[str], flags: int, mode: int = 0o777) -> int:
        """The file opened as asked (so O_TRUNC does what it does), but written on /dev/full."""
        fd = real_open(file, flags, mode)
        if not flags & os.O_WRONLY:
            return fd
        os.close(fd)
        return real_open("/dev/full", os.O_WRONLY)

    monkeypatch.setattr(os, "open", full_disk)
    with pytest.raises(OSError) as raised:
        write_private(path, 'data_dir = "/elsewhere"\n' * 100)
    monkeypatch.undo()
    assert raised.value.errno == errno.ENOSPC
    assert path.read_text() == 'data_dir = "/data"\n'
    assert [p.name for p in tmp_path.iterdir()] == ["machine.toml"]  # no temp file left


def test_the_childs_file_is_owner_only(tmp_path: Path) -> None:
    path = tmp_path / "zenoh-child.json5"
    write_private(path, "{}")
    write_private(path, '{mode: "client"}')
    assert path.read_text() == '{mode: "client"}'
    assert path.stat().st_mode & 0o777 == 0o600
