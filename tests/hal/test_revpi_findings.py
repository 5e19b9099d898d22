"""The RevPi backend's findings: every wrong or missing IO, a broken piCtory config or process
image, a clear finding rather than a traceback (moved from test_revpi.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from ride_machine.hal.base import Outputs
from ride_machine.hal.iomap import IoMap
from ride_machine.hal.revpi import RevPiConfigError, RevPiHal, check_revpi_io
from ride_machine.schema.findings import Finding, Severity
from tests.fixtures.revpi import (
    address,
    find_entry,
    load,
    read_bit,
    write_bit,
    write_config,
)
from tests.hal.test_revpi import CONFIG, MAP, relay_byte


# -- findings -----------------------------------------------------------------------------
def errors(findings: list[Finding]) -> list[tuple[str, str]]:
    return [(f.category, f.path) for f in findings if f.severity is Severity.ERROR]


@pytest.mark.hazard("H48")
@pytest.mark.parametrize(
    ("field", "channel", "category", "words"),
    [
        ("estop", "O_5", "io_type", "digital output"),
        ("tiltPosition", "I_5", "io_type", "digital input"),
        ("tiltHome", "InputValue_2", "io_type", "16-bit input"),
        ("rotateRelay", "I_6", "io_type", "digital input"),
        ("tiltDir", "OutputValue_1", "io_type", "16-bit output"),
        ("rotateHome", "InputDebounce", "io_type", "memory value"),
        ("rotateRelay", "O_99", "io_missing", "candidates: O_1"),
        ("estop", "EStop", "io_missing", "digital input"),
        ("tiltPosition", "__class__", "io_missing", "analog input"),
    ],
)
def test_wrong_or_missing_io_is_a_finding(
    image: str, field: str, channel: str, category: str, words: str
) -> None:
    iomap = IoMap.model_validate({field: channel})
    findings = check_revpi_io(iomap, CONFIG, image)
    assert errors(findings) == [(category, f"/hal/iomap/{field}")]
    assert words in findings[0].message
    assert channel in findings[0].message
    before = Path(image).read_bytes()
    with pytest.raises(RevPiConfigError) as exc:
        RevPiHal(iomap, image, CONFIG)
    assert errors(exc.value.findings) == [(category, f"/hal/iomap/{field}")]
    assert Path(image).read_bytes() == before  # a config that does not fit touches nothing


def test_every_bad_signal_is_reported_at_once(image: str) -> None:
    iomap = IoMap.model_validate({"estop": "O_5", "tiltPosition": "nope", "tiltRelay": "I_9"})
    paths = sorted(path for _, path in errors(check_revpi_io(iomap, CONFIG, image)))
    assert paths == ["/hal/iomap/estop", "/hal/iomap/tiltPosition", "/hal/iomap/tiltRelay"]


@pytest.mark.parametrize(
    ("content", "words"),
    [
        ("", "not valid JSON"),
        ('{ "App": ', "not valid JSON"),
        ("[1, 2]", "not a JSON object"),
        ('{"App": {}, "Summary": {}}', "Devices"),
        ('{"App": {}, "Summary": {}, "Devices": {}}', "Devices"),
        ('{"App": {}, "Summary": {}, "Devices": [7]}', "device #0"),
        ('{"App": {}, "Summary": {}, "Devices": [{"name": "x"}]}', "lacks type"),
    ],
)
def test_broken_config_rsc_is_a_clear_finding(
    tmp_path: Path, image: str, content: str, words: str
) -> None:
    path = tmp_path / "config.rsc"
    path.write_text(content, encoding="utf-8")
    findings = check_revpi_io(MAP, str(path), image)
    assert errors(findings) == [("revpi_config", "/hal/revpi/configrsc")]
    assert words in findings[0].message
    with pytest.raises(RevPiConfigError, match="configrsc"):
        RevPiHal(MAP, image, str(path))


def test_binary_config_rsc_is_a_finding(tmp_path: Path, image: str) -> None:
    path = tmp_path / "config.rsc"
    path.write_bytes(b"\xff\xfe\x00garbage")
    findings = check_revpi_io(MAP, str(path), image)
    assert errors(findings) == [("revpi_config", "/hal/revpi/configrsc")]


def test_missing_config_rsc_is_a_finding(tmp_path: Path, image: str) -> None:
    findings = check_revpi_io(MAP, str(tmp_path / "nowhere.rsc"), image)
    assert errors(findings) == [("revpi_config", "/hal/revpi/configrsc")]
    assert "cannot read" in findings[0].message


def test_config_revpimodio_rejects_is_a_finding(tmp_path: Path, image: str) -> None:
    data = load()
    find_entry(data, "O_2")[2] = "one"  # a bit length revpimodio2 cannot read
    findings = check_revpi_io(MAP, write_config(tmp_path, data), image)
    assert errors(findings) == [("revpi_config", "/hal/revpi/configrsc")]
    assert "revpimodio2 rejects" in findings[0].message


def test_offset_that_is_not_a_number_is_a_layout_finding(tmp_path: Path, image: str) -> None:
    data = load()
    data["Devices"][1]["offset"] = "eleven"
    findings = check_revpi_io(MAP, write_config(tmp_path, data), image)
    assert errors(findings) == [("revpi_layout", "/hal/revpi/configrsc")]
    assert "'eleven', not a number" in findings[0].message


def test_a_module_missing_from_the_config_makes_its_ios_missing(tmp_path: Path, image: str) -> None:
    data = load()
    data["Devices"] = [d for d in data["Devices"] if d["name"] != "aio"]
    findings = check_revpi_io(MAP, write_config(tmp_path, data), image)
    assert errors(findings) == [("io_missing", "/hal/iomap/tiltPosition")]


@pytest.mark.hazard("H43")
def test_relay_defaulting_on_is_a_warning(tmp_path: Path, image: str) -> None:
    data = load()
    find_entry(data, "O_2")[1] = "1"
    findings = check_revpi_io(MAP, write_config(tmp_path, data), image)
    assert [(f.category, f.severity, f.path) for f in findings if f.category != "io_shared"] == [
        ("io_default", Severity.WARNING, "/hal/iomap/rotateDir")
    ]
    h = RevPiHal(MAP, image, write_config(tmp_path, data))  # a warning does not stop it
    try:
        assert relay_byte(image) == 0  # safe means off, whatever the default says
    finally:
        h.close()


@pytest.mark.hazard("H48")
def test_unmapped_outputs_are_never_written_not_even_their_default(
    tmp_path: Path, image: str
) -> None:
    data = load()
    find_entry(data, "O_8")[1] = "1"
    find_entry(data, "PWM_1")[1] = "50"
    h = RevPiHal(MAP, image, write_config(tmp_path, data))
    try:
        h.scan_outputs(Outputs(ro={"O_1": True}))
        assert read_bit(image, "O_8") is False  # piControl applies defaults, not the daemon
        assert Path(image).read_bytes()[address("PWM_1")[0]] == 0
        write_bit(image, "O_7", True)  # another program drives O_7 in our byte
        h.scan_outputs(Outputs(ro={"O_1": False, "O_2": True}))
        assert relay_byte(image) == 0b0100_0010
        h.force_all_outputs_safe()
        assert relay_byte(image) == 0b0100_0000  # the relays off, O_7 as it was
    finally:
        h.close()
    assert relay_byte(image) == 0b0100_0000


def test_overlapping_modules_are_one_clear_error(tmp_path: Path, image: str) -> None:
    data = load()
    data["Devices"][2]["offset"] = 120  # the AIO overlaps the DIO's last bytes
    findings = check_revpi_io(MAP, write_config(tmp_path, data), image)
    assert errors(findings) == [
        ("revpi_layout", "/hal/revpi/configrsc"),
        ("io_missing", "/hal/iomap/tiltPosition"),  # InputValue_1 lies in the overlap
    ]
    assert "overlap at bytes 120–123" in findings[0].message
    assert "must start at byte 124" in findings[0].message
    missing = next(f for f in findings if f.category == "io_missing")
    assert "revpimodio2 ignored it" in missing.message
    notes = [f.message for f in findings if f.category == "revpi_config"]
    assert notes == ["revpimodio2 ignores 2 IO(s) that lie in the overlap above"]


def _short_image(directory: Path) -> str:
    path = directory / "short"
    path.write_bytes(bytes(100))
    return str(path)


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda d: str(d / "absent"), "no process image"),
        (str, "not a process image"),
        (_short_image, "needs 213"),
        (lambda d: "/dev/null", "gives no data at byte 212"),  # validate once said it would run
    ],
)
def test_bad_process_image_is_a_finding(
    tmp_path: Path, make: Callable[[Path], str], words: str
) -> None:
    procimg = make(tmp_path)
    findings = check_revpi_io(MAP, CONFIG, procimg)
    assert errors(findings) == [("revpi_procimg", "/hal/revpi/procimg")]
    assert words in findings[0].message
    with pytest.raises(RevPiConfigError, match="procimg"):
        RevPiHal(MAP, procimg, CONFIG)


def test_no_config_and_none_at_the_known_places_is_a_finding(image: str) -> None:
    if any(Path(p).exists() for p in ("/etc/revpi/config.rsc", "/opt/KUNBUS/config.rsc")):
        pytest.skip("this host has a piCtory config")
    findings = check_revpi_io(MAP, None, image)
    assert errors(findings) == [("revpi_config", "/hal/revpi/configrsc")]
    assert "/etc/revpi/config.rsc" in findings[0].message


def test_findings_serialise_for_the_wire(image: str) -> None:
    findings = check_revpi_io(IoMap(estop="O_5"), CONFIG, image)
    wire = json.loads(json.dumps([f.model_dump(mode="json") for f in findings]))
    assert wire[0]["category"] == "io_type"
    assert wire[0]["severity"] == "error"


def test_package_imports_without_revpimodio2() -> None:
    code = (
        "import sys; sys.modules['revpimodio2'] = None\n"
        "import hal.revpi, sim.procimg\n"
        "from ride_machine.hal.iomap import IoMap\n"
        "f = hal.revpi.check_revpi_io(IoMap(), sys.argv[1], sys.argv[1])\n"
        "print(f[-1].category)\n"
        "try:\n"
        "    hal.revpi.RevPiHal(IoMap(), sys.argv[1], sys.argv[1])\n"
        "except hal.revpi.RevPiConfigError as e:\n"
        "    print(e.findings[0].category)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, CONFIG],
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
        cwd=Path(__file__).parents[2],
    )
    assert out.stdout.split() == ["revpi_unavailable", "revpi_unavailable"]
