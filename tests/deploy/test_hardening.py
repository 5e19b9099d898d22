"""Every service of compose.yaml and of its override files is hardened by default (issue 57,
point 3): a read-only root with a tmpfs for /tmp, no capabilities, no privilege gained through
exec, a bound on processes and a memory limit above the peak measured in docs/deploy.md.

Here the files as written (and merged, `-f compose.yaml -f docker/…`); what each compose
implementation hands its engine is in test_compose_readers.py, what a running container gets in
test_container.py.
"""

from __future__ import annotations

import re
from typing import Any

import pytest

from tests.deploy import spec
from tests.procs import REPO

OVERRIDES = {
    "plant": spec.PLANT_OVERRIDE,
    "revpi": spec.REVPI_OVERRIDE,
    "router": spec.ROUTER_OVERRIDE,
    "gateway": REPO / "docker" / "compose.gateway.yaml",
}
ENV = {"PICONTROL_GID": "996"}  # docker/compose.revpi.yaml asks for it
NO_NEW_PRIVILEGES = "no-new-privileges:true"
PIDS_MAX = 1024
MARGIN = 2.0
"""A memory limit at least this many times the service's measured peak."""
_UNITS = {"k": 1 << 10, "m": 1 << 20, "g": 1 << 30}
_PEAK_ROW = re.compile(r"^\| `(?P<service>[a-z]+)` \|[^|]*\| (?P<peak>[0-9.]+) MB \|", re.M)


def services() -> dict[str, dict[str, Any]]:
    """`<file>/<service>` → each service as compose runs it with that file (merged)."""
    base = spec.load_compose(env=ENV)
    out = {f"compose.yaml/{n}": s for n, s in base["services"].items()}
    for label, path in OVERRIDES.items():
        merged = spec.merged(base, spec.load_compose(path, ENV))
        for name, svc in merged["services"].items():
            out[f"{label}/{name}"] = svc
    return out


def memory_bytes(value: str | int) -> int:
    m = re.fullmatch(r"([0-9]+)([kmg]?)b?", str(value).lower())
    assert m, f"not a memory size: {value!r}"
    return int(m[1]) * _UNITS.get(m[2], 1)


def measured_peaks() -> dict[str, float]:
    """Service → its peak memory in MB, from docs/deploy.md's "Hardening" table."""
    text = (REPO / "docs" / "deploy.md").read_text()
    return {m["service"]: float(m["peak"]) for m in _PEAK_ROW.finditer(text)}


@pytest.mark.parametrize("where", sorted(services()))
def test_every_service_is_hardened_by_default(where: str) -> None:
    svc = services()[where]
    assert svc.get("read_only") is True, f"{where}: the root file system is writable"
    assert "/tmp" in (svc.get("tmpfs") or []), f"{where}: no tmpfs for /tmp on a read-only root"
    assert svc.get("cap_drop") == ["ALL"], where
    assert not svc.get("cap_add") and not svc.get("privileged"), where
    assert NO_NEW_PRIVILEGES in (svc.get("security_opt") or []), where
    assert 0 < int(svc.get("pids_limit", 0)) <= PIDS_MAX, f"{where}: no bound on processes"
    assert "mem_limit" in svc, f"{where}: no memory limit"


def test_each_memory_limit_is_above_its_measured_peak() -> None:
    peaks = measured_peaks()
    limits = {
        where.split("/")[1]: memory_bytes(svc["mem_limit"]) for where, svc in services().items()
    }
    assert set(peaks) == set(limits), "docs/deploy.md measures every service, and only those"
    for name, peak_mb in peaks.items():
        assert limits[name] >= MARGIN * peak_mb * 1e6, f"{name}: {limits[name]} B for {peak_mb} MB"


def test_nothing_but_volumes_and_tmpfs_is_written() -> None:
    """What the services write lives on a named volume, a tmpfs or /dev/shm: the daemon's data
    dir, the plant's process image, the supervisor's private socket and the heartbeat file."""
    machine = spec.service(spec.load_compose(), "machine")
    volumes = {m.target for m in spec.mounts(machine) if not m.is_bind}
    args = spec.parse_cli(spec.command(machine))
    assert str(args.data_dir) in volumes
    assert spec.environment(machine)["MACHINE_HEARTBEAT_FILE"].startswith("/dev/shm/")
    plant = spec.service(spec.load_compose(spec.PLANT_OVERRIDE), "plant")
    assert "/run/plant" in {m.target for m in spec.mounts(plant) if not m.is_bind}
