from __future__ import annotations

import pytest

from tests.rig import Rig


def pytest_configure(config: pytest.Config) -> None:
    """Zenoh's runtime in this process as a Rider lays it out (one worker thread,
    `rider.client.open_session`): the first session fixes it for every later one, so it is
    fixed here, not by whichever test happens to open a session first."""
    import zenoh

    from rider.client import open_session

    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    open_session(conf).close()


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
