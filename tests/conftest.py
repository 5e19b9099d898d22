from __future__ import annotations

import os
import random
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.fixtures.revpi import make_image
from tests.procs import logs_since
from tests.rig import Rig


def pytest_configure(config: pytest.Config) -> None:
    order = str(config.getoption("--order"))
    if order not in ("normal", "reverse") and not order.startswith("random"):
        raise pytest.UsageError(f"--order: {order!r} is not normal, reverse or random[:SEED]")
    if order.startswith("random"):
        _seed(config)  # before pytest-xdist starts its workers
    _configure_zenoh()


def _configure_zenoh() -> None:
    """Zenoh's runtime in this process as a Rider lays it out (one worker thread,
    `rider.client.open_session`): the first session fixes it for every later one, so it is
    fixed here, not by whichever test happens to open a session first."""
    import zenoh

    from ride_machine.rider.client import open_session

    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", "[]")
    open_session(conf).close()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--order",
        default="normal",
        help="run the tests in 'normal', 'reverse' or 'random' (or 'random:SEED') order,"
        " to find tests that lean on another's leftovers (make test-under-load)",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    order = str(config.getoption("--order"))
    if order == "reverse":
        items.reverse()
    elif order.startswith("random"):
        random.Random(_seed(config)).shuffle(items)


def _seed(config: pytest.Config) -> str:
    """The random order's seed: given (`random:SEED`) or drawn once per run. The run's
    pytest-xdist workers collect in the same order: they inherit the seed drawn first, at
    configure time, through the environment."""
    if _SEED not in config.stash:
        order = str(config.getoption("--order"))
        drawn = os.environ.get(SEED_ENV) or str(random.randrange(10**6))
        config.stash[_SEED] = order.partition(":")[2] or drawn
        os.environ[SEED_ENV] = config.stash[_SEED]
    return config.stash[_SEED]


SEED_ENV = "RIDE_TEST_ORDER_SEED"


_SEED = pytest.StashKey[str]()


def _order_line(config: pytest.Config) -> str:
    order = str(config.getoption("--order"))
    if order.startswith("random"):
        seed = _seed(config)
        return f"test order: random, seed {seed} (again: --order random:{seed})"
    return f"test order: {order}"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """A failed test's report carries the ends of its daemons' logs: a fault's message, a
    stall, a refusal the daemon logged (a CI run leaves nothing else behind to read)."""
    outcome = yield
    report = outcome.get_result()  # type: ignore[attr-defined]
    if report.failed and call.when == "call":
        for title, text in logs_since(call.start):
            report.sections.append((title, text))


def pytest_report_header(config: pytest.Config) -> str:
    return _order_line(config)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    if str(terminalreporter.config.getoption("--order")) != "normal":
        terminalreporter.write_line(_order_line(terminalreporter.config))


@pytest.fixture(autouse=True)
def _stop_signals_as_they_were() -> Iterator[None]:
    """SIGINT and SIGTERM as before each test: product code run on pytest's own main thread
    (the daemon, the UI server) leaves them ignored once it has served, and every process a
    later test of this worker starts would inherit an ignored signal across exec (a Ctrl-C
    sent to it then does nothing)."""
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for sig, handler in saved.items():
        if handler is not None and signal.getsignal(sig) is not handler:
            signal.signal(sig, handler)


@pytest.fixture
def rig() -> Rig:
    return Rig()


@pytest.fixture
def ready_rig() -> Rig:
    return Rig().ready()


@pytest.fixture
def image(tmp_path: Path) -> str:
    """A fresh process-image file beside the piCtory fixture (tests/fixtures/revpi), for the
    RevPi backend and the process-image simulator."""
    return make_image(tmp_path)


@pytest.fixture
def daemon(tmp_path):  # type: ignore[no-untyped-def]
    """A real `machine run --sim` process on a free loopback port."""
    from tests.procs import running_daemon

    with running_daemon(tmp_path) as d:
        yield d
