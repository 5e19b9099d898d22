"""docker/compose.plant.yaml, read without an engine (issue 53): the simulated plant a service
of its own beside the machine. tests/deploy/test_topology.py replays it in namespaces."""

from __future__ import annotations

from typing import Any

from ride_machine.sim.plant import parse as plant_parse
from tests.deploy import spec


def test_the_plant_overlay_gives_the_simulated_ride_a_container_of_its_own() -> None:
    compose: dict[str, Any] = spec.load_compose()
    """docker/compose.plant.yaml (issue 53): `docker compose pause machine` must not stop the
    plant's clock, so the plant is a service of its own, on the machine's own config, and the
    supervisor attaches to it through one named volume; nothing else of the machine changes."""
    both = spec.merged(compose, spec.load_compose(spec.PLANT_OVERRIDE))
    plant_svc = spec.service(both, "plant")
    argv = spec.command(plant_svc)
    assert argv[:3] == ["python", "-m", "ride_machine.sim.plant"]
    plant_args = plant_parse(argv[3:])
    assert plant_args.make_image
    machine_svc = spec.service(both, "machine")
    machine_argv = spec.command(machine_svc)
    machine_args = spec.parse_cli(machine_argv)
    assert (machine_args.cmd, machine_args.hal, machine_args.plant) == (
        "supervise",
        "sim",
        plant_args.dir,
    )
    for svc in (plant_svc, machine_svc):
        volume = {m.target: m for m in spec.mounts(svc)}[str(plant_args.dir)]
        assert (volume.is_bind, volume.read_only, volume.source) == (False, False, "plant")
    assert "plant" in both["volumes"]
    config = {m.target: m for m in spec.mounts(plant_svc)}[str(plant_args.config)]
    assert config.source == "./machine.toml" and config.read_only
    at = machine_argv.index("--plant")
    assert machine_argv[:at] + machine_argv[at + 2 :] == spec.command(
        spec.service(compose, "machine")
    )
    assert plant_svc["restart"] == "unless-stopped" and plant_svc["logging"]["driver"]
