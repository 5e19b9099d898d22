"""HAL backends by name: the one lookup finds the simulator and the RevPi, the config validates
each backend's table with the model it registers, and the simulator's refusals reach the bus
as the wire errors they were."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pydantic import ValidationError

from ride_machine.hal.backends import Backend, NoBackend, backend
from ride_machine.hal.base import Hal
from ride_machine.hal.iomap import IoMap
from ride_machine.hal.revpibackend import RevPiSettings
from ride_machine.schema.errors import ErrorCode
from ride_machine.schema.sim import SimEstop, SimWorldState
from ride_machine.service.config.load import load_data
from ride_machine.service.config.model import HalBackend, HalSection, MachineConfig
from ride_machine.service.errors import Rejected
from ride_machine.service.supervision.simport import sim_port
from ride_machine.sim.settings import PhysicsParams
from ride_machine.sim.world import CONFIG_RSC, SimWorld, make_image
from tests.fixtures.revpi import address
from tests.rig import FakeClock


def test_every_configurable_backend_is_registered_with_its_table() -> None:
    for name in HalBackend:
        found = backend(name)
        assert isinstance(found, Backend)
        assert type(HalSection().table(name)) is found.settings  # its table, by its model
    assert backend(HalBackend.SIM).settings is PhysicsParams
    assert backend(HalBackend.REVPI).settings is RevPiSettings


def test_an_unknown_backend_is_refused_by_name() -> None:
    with pytest.raises(NoBackend, match=r"no HAL backend 'ethercat' .*revpi, sim"):
        backend("ethercat")


def test_the_config_checks_hal_sim_with_the_registered_model() -> None:
    config, report = load_data({"hal": {"sim": {"rotate_speed_dps": 0, "wings": 2}}})
    assert config is None
    paths = {f.path for f in report.findings}
    assert {"/hal/sim/rotate_speed_dps", "/hal/sim/wings"} <= paths
    config, report = load_data({"hal": {"sim": {"seed": 7}}})
    assert config is not None and report.ok
    assert config.hal.sim == PhysicsParams(seed=7)
    assert config.hal.settings() is config.hal.sim


def test_the_simulator_opens_safe_and_injects_faults() -> None:
    clock = FakeClock()
    config = MachineConfig()
    sim = backend(HalBackend.SIM)
    hal = sim.open(config.hal.iomap, config.hal.sim, clock, None)
    assert isinstance(hal, Hal)
    assert not hal.read_estop()
    faults = sim.simulator(hal)
    assert faults is not None
    faults.apply(faults.decode("estop", b'{"pressed": true}', "application/json"))
    assert hal.read_estop()
    world = faults.world(12.5)
    assert isinstance(world, SimWorldState)
    assert world.estop_pressed and world.time == 12.5 and not any(world.relays.values())


def test_hardware_has_no_simulator(tmp_path: Path) -> None:
    revpi = backend(HalBackend.REVPI)
    opened = backend(HalBackend.SIM).open(IoMap(), PhysicsParams(), FakeClock(), None)
    assert revpi.simulator(opened) is None  # not one of its own: nothing to inject into
    assert revpi.world(IoMap(), RevPiSettings(), tmp_path, 0.01) is None
    assert list(tmp_path.iterdir()) == []


def test_the_world_runs_in_a_plant_process_of_its_own(tmp_path: Path) -> None:
    """Issue 53: the simulated plant keeps its own clock, so nothing that stops the
    controller's processes stops it; it answers faults and the truth over its socket."""
    iomap = IoMap(chargePump="O_5")
    world = backend(HalBackend.SIM).world(iomap, PhysicsParams(), tmp_path, 0.005)
    assert world is not None
    assert Path(world.procimg).parent == tmp_path and Path(world.configrsc).is_file()
    world.start()
    try:
        pid = world.pid
        assert pid is not None and pid != os.getpid()
        assert b"sim.plant" in Path(f"/proc/{pid}/cmdline").read_bytes()
        world.apply(SimEstop(pressed=True))
        world.step_now()
        state = world.world(0.0)
        assert state.estop_pressed
        assert state.drives_powered is False  # nothing toggles the pump: the relay is down
        assert state.clock is not None and abs(state.clock - time.monotonic()) < 1.0
    finally:
        world.stop()
    assert not Path(f"/proc/{pid}").exists() or b"Z" in Path(f"/proc/{pid}/stat").read_bytes()


def test_a_simulator_refusal_reaches_the_bus_as_its_wire_error() -> None:
    hal = backend(HalBackend.SIM).open(IoMap(), PhysicsParams(), FakeClock(), None)
    port = sim_port(backend(HalBackend.SIM).simulator(hal))
    assert port is not None
    with pytest.raises(Rejected) as unknown:
        port.decode("fly", b"{}", None)
    assert unknown.value.code is ErrorCode.UNKNOWN_COMMAND
    assert unknown.value.message.startswith("unknown sim key 'fly'; known: estop, ")
    with pytest.raises(Rejected) as bad:
        port.decode("estop", b'{"pressed": "maybe"}', "application/json")
    assert (bad.value.code, bad.value.path) == (ErrorCode.BAD_PAYLOAD, "/pressed")
    assert sim_port(None) is None


def test_a_late_step_of_the_world_is_counted_and_said_at_most_once_a_second(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The supervised simulator's field stood still while its thread waited on a loaded host,
    and the daemon faulted a tilt that did not follow: the supervisor's log says so now, and
    the world's state counts it (a test tells the rig's lateness from the daemon's fault)."""
    clock = FakeClock()
    world = SimWorld(
        IoMap(), make_image(tmp_path / "procimg"), str(CONFIG_RSC), PhysicsParams(), 0.005, clock
    )
    try:
        with caplog.at_level(logging.WARNING, logger="ride_machine.sim.world"):
            world._late(clock(), 0.01)  # within LATE_S: a step as planned
            world._late(clock(), 0.08)
            world._late(clock(), 0.05)  # the same second: counted, not said again
            world._late(clock.advance(1.5), 0.04)
        state = world.world(clock())
    finally:
        world.stop()
    assert (world.late_steps, world.longest_late_s) == (3, 0.08)
    assert (state.late_steps, state.longest_late_s) == (3, 0.08)  # `sim/world` tells a test
    said = [r.getMessage() for r in caplog.records if "sim_world_late" in r.getMessage()]
    assert len(said) == 2 and "late_s=0.080 late_steps=1" in said[0], said


def test_the_supervised_world_holds_the_rotate_in_its_arc_until_a_scan_has_seen_it(
    tmp_path: Path,
) -> None:
    """Run 46 (a loaded host, the tests' 720°/s, a 30° arc: 0.042 s closed a turn): the scan
    stalled across the arc, missed the edge, and a supervised ride stopped ROTATE_HOME_TIMEOUT.
    The world now waits at the far end of the arc until a scan that began after the switch
    closed has completed, as the embedded world does by construction; never longer than
    `ARC_HOLD_MAX_S` (a frozen daemon's rotate turns on, as a real ride's would)."""
    clock = FakeClock()
    params = PhysicsParams(rotate_speed_dps=720.0, home_arc_deg=30.0, start_rotate_deg=350.0)
    image = make_image(tmp_path / "procimg")
    world = SimWorld(IoMap(), image, str(CONFIG_RSC), params, 0.005, clock)
    scans = [7]
    world.follow_scans(lambda: scans[0])
    byte, bit = address("O_1", CONFIG_RSC)  # the rotate relay, on
    assert bit is not None
    with open(image, "r+b") as f:
        f.seek(byte)
        f.write(bytes([1 << bit]))
    try:

        def run(seconds: float) -> float:
            for _ in range(round(seconds / 0.005)):
                clock.advance(0.005)
                world.step_now()
            return world.world(clock()).rotate_deg

        assert run(0.03) == pytest.approx(11.6, abs=0.1)  # closed at 0° (0.014 s), turning on
        assert run(0.1) == pytest.approx(29.0)  # held at the arc's end: the daemon has not scanned
        scans[0] = 8  # a scan that may have read the image before it closed
        assert run(0.1) == pytest.approx(29.0)
        scans[0] = 9  # one that began after: it saw the switch closed
        assert run(0.01) == pytest.approx(36.2, abs=0.1)  # and the world turns on
        # The next arc, 0.45 s on; the daemon stalls from here: held for ARC_HOLD_MAX_S only.
        assert run(0.5) == pytest.approx(29.0)
        assert run(0.4) == pytest.approx(29.0)
        assert run(0.2) > 60.0  # a frozen daemon's rotate turns on (the freeze tests' hazard)
    finally:
        world.stop()


# The daemon's whole import and start-up path with the RevPi backend: the CLI, the daemon, the
# supervisor and its field, the config with a [hal.sim] table it does not use, its checks and
# the backend lookup. Run in a fresh interpreter: this one has loaded the simulator.
HARDWARE_ONLY = """
import sys
import ride_machine.service.cli
import ride_machine.service.supervision.daemon
import ride_machine.service.supervision.supervisor
import ride_machine.service.supervision.field
from ride_machine.hal.backends import backend
from ride_machine.service.config.load import load_data
from ride_machine.service.config.validate import semantic_findings
config, report = load_data({"hal": {"backend": "revpi", "sim": {"seed": 3}}})
assert config is not None and report.ok, report
semantic_findings(config)
assert config.hal.settings().procimg == "/dev/piControl0"
backend(config.hal.backend)
print(sorted(m for m in sys.modules if m.split(".")[:2] == ["ride_machine", "sim"]))
"""


def test_the_daemon_with_the_revpi_backend_loads_no_simulator() -> None:
    """Issue 54: importing `service.config.model` loaded `sim`, `sim.backend` and
    `sim.settings` (the config typed `[hal.sim]` with the simulator's model)."""
    done = subprocess.run(
        [sys.executable, "-c", HARDWARE_ONLY],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_a_table_for_no_registered_backend_is_refused_where_it_is() -> None:
    config, report = load_data({"hal": {"ethercat": {"cycle_us": 250}}})
    assert config is None
    assert [f.path for f in report.findings] == ["/hal/ethercat"]
    assert "no registered HAL backend (known: revpi, sim)" in report.findings[0].message
    config, report = load_data({"hal": {"backend": "ethercat"}})
    assert config is None and [f.path for f in report.findings] == ["/hal/backend"]


def test_only_the_chosen_backends_table_is_checked_as_the_config_loads() -> None:
    """A RevPi machine does not validate (or load) the simulator for its `[hal.sim]`; reading
    that table validates it then, with its path."""
    config, report = load_data({"hal": {"backend": "revpi", "sim": {"rotate_speed_dps": 0}}})
    assert config is not None and report.ok
    with pytest.raises(ValidationError) as bad:
        _ = config.hal.sim
    assert bad.value.errors()[0]["loc"] == ("sim", "rotate_speed_dps")
