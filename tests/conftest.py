from __future__ import annotations

import pytest

from tests.rig import Rig


@pytest.fixture
def rig() -> Rig:
    return Rig()


@pytest.fixture
def ready_rig() -> Rig:
    return Rig().ready()


@pytest.fixture
def daemon(tmp_path):  # type: ignore[no-untyped-def]
    """A real `machine run --sim` process on a free loopback port."""
    from tests.procs import running_daemon

    with running_daemon(tmp_path) as d:
        yield d
