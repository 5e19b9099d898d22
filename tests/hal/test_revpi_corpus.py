"""The RevPi backend on a corpus of piCtory layouts modelled on real configs (real revpimodio2,
a process-image file, no hardware): renamed IOs, an AIO left of the base, gateways, Connect 4 +
RO, Compact, broken offsets, default-1 outputs, a relay module shared with other signals."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from ride_machine.hal.base import Outputs
from ride_machine.hal.iomap import DIGITAL_INPUTS, RELAY_OUTPUTS, IoMap, Signal
from ride_machine.hal.revpi import RevPiConfigError, RevPiHal, check_revpi_io
from ride_machine.schema.commands import Command
from ride_machine.schema.findings import Finding, Severity
from ride_machine.schema.status import MachineState
from tests.fixtures.revpi import IMAGE_BYTES, address, load, make_image, write_config
from tests.fixtures.revpi.corpus import LAYOUTS, path, render
from tests.hal.test_revpi import RevPiRide
from tests.hal.test_revpi_findings import errors

pytest.importorskip("revpimodio2")

RENAMED = IoMap.model_validate(
    {
        "rotateHome": "rot_home",
        "tiltHome": "tilt_home",
        "estop": "estop_ok",
        "tiltPosition": "tilt_pos",
        "rotateRelay": "rot_run",
        "rotateDir": "rot_ccw",
        "tiltRelay": "tilt_run",
        "tiltDir": "tilt_up",
    }
)
RO_RELAYS = IoMap.model_validate(
    {
        "rotateRelay": "RelayOutput_1_i03",
        "rotateDir": "RelayOutput_2_i03",
        "tiltRelay": "RelayOutput_3_i03",
        "tiltDir": "RelayOutput_4_i03",
    }
)
COMPACT = IoMap.model_validate(
    {
        "rotateHome": "DIn_i01.0",
        "tiltHome": "DIn_i01.1",
        "estop": "DIn_i01.2",
        "tiltPosition": "AIn_1",
        "rotateRelay": "DOut.0",
        "rotateDir": "DOut.1",
        "tiltRelay": "DOut.2",
        "tiltDir": "DOut.3",
    }
)
WORKING = {
    "renamed": RENAMED,
    "aio_left": IoMap(),
    "connect4_ro": RO_RELAYS,
    "compact": COMPACT,
    "shared_dio": IoMap(),
}
"""The layouts a ride can run on, with the IO map that fits each."""


def where(layout: str, channel: str) -> tuple[int, int | None]:
    """(byte, bit) of a channel from the corpus file itself (not from revpimodio2)."""
    name, _, bit = channel.rpartition(".")
    if bit.isdigit():
        byte, _ = address(name, Path(path(layout)))
        return byte + int(bit) // 8, int(bit) % 8
    return address(channel, Path(path(layout)))


def random_image(directory: Path, seed: int) -> str:
    """An image as a live machine leaves it: every byte some value (inputs, other outputs)."""
    rng = random.Random(seed)
    image = directory / "procimg"
    image.write_bytes(bytes(rng.randrange(256) for _ in range(IMAGE_BYTES)))
    return str(image)


def set_bit(image: str, byte: int, bit: int, on: bool) -> None:
    data = bytearray(Path(image).read_bytes())
    data[byte] = data[byte] | 1 << bit if on else data[byte] & ~(1 << bit)
    Path(image).write_bytes(bytes(data))


def changed(before: bytes, after: bytes) -> dict[int, int]:
    """Byte → the bits that differ."""
    return {i: before[i] ^ after[i] for i in range(len(before)) if before[i] != after[i]}


@pytest.fixture(params=sorted(WORKING))
def layout(request: pytest.FixtureRequest) -> str:
    name: str = request.param
    return name


def test_corpus_files_are_current() -> None:
    for name in LAYOUTS:
        assert Path(path(name)).read_text(encoding="utf-8") == render(name), name


# -- the layouts that fit: no surprise writes, every IO at its byte and bit -----------------
def test_each_working_layout_checks_without_errors(layout: str, tmp_path: Path) -> None:
    findings = check_revpi_io(WORKING[layout], path(layout), make_image(tmp_path))
    assert errors(findings) == []


def test_open_scan_and_close_write_only_our_relay_bits(layout: str, tmp_path: Path) -> None:
    iomap = WORKING[layout]
    image = random_image(tmp_path, seed=len(layout))
    ours: dict[int, int] = {}
    for s in RELAY_OUTPUTS:
        byte, bit = where(layout, iomap.channel(s))
        assert bit is not None
        ours[byte] = ours.get(byte, 0) | 1 << bit
    before = Path(image).read_bytes()
    hal = RevPiHal(iomap, image, path(layout))
    try:
        # Opening cleared our relays and touched no other bit (not the base's RS485 limits,
        # not the other outputs of the relays' module, not their piCtory defaults).
        diff = changed(before, Path(image).read_bytes())
        assert all(byte in ours and bits & ~ours[byte] == 0 for byte, bits in diff.items())
        for s in RELAY_OUTPUTS:
            opened = Path(image).read_bytes()
            hal.scan_outputs(Outputs(ro={iomap.channel(s): True}))
            byte, bit = where(layout, iomap.channel(s))
            assert changed(opened, Path(image).read_bytes()) == {byte: 1 << (bit or 0)}
            hal.scan_outputs(Outputs(ro={}))
            assert Path(image).read_bytes() == opened
        hal.scan_outputs(Outputs(ro={iomap.channel(s): True for s in RELAY_OUTPUTS}))
    finally:
        hal.close()
    after = Path(image).read_bytes()
    assert all(after[b] & m == 0 for b, m in ours.items())  # closed safe
    diff = changed(before, after)
    assert all(byte in ours and bits & ~ours[byte] == 0 for byte, bits in diff.items())


def test_each_digital_input_is_read_from_its_bit(layout: str, tmp_path: Path) -> None:
    iomap = WORKING[layout]
    image = make_image(tmp_path)
    hal = RevPiHal(iomap, image, path(layout))
    try:
        for s in DIGITAL_INPUTS:
            byte, bit = where(layout, iomap.channel(s))
            assert bit is not None
            set_bit(image, byte, bit, True)
            di = hal.scan_inputs().di
            assert [ch for ch, on in di.items() if on] == [iomap.channel(s)]
            assert hal.read_estop() is ((s is Signal.ESTOP) != iomap.estop_active_low)
            set_bit(image, byte, bit, False)
    finally:
        hal.close()


def test_the_tilt_position_word_is_read(layout: str, tmp_path: Path) -> None:
    iomap = WORKING[layout]
    image = make_image(tmp_path)
    byte, bit = where(layout, iomap.tilt_position)
    assert bit is None
    with open(image, "r+b") as fh:
        fh.seek(byte)
        fh.write((1680).to_bytes(2, "little"))
    hal = RevPiHal(iomap, image, path(layout))
    try:
        assert hal.scan_inputs().ai == {iomap.tilt_position: 1680}
    finally:
        hal.close()


def test_aio_left_of_the_base_moves_every_address(tmp_path: Path) -> None:
    assert where("aio_left", "InputValue_1") == (0, None)
    assert where("aio_left", "RS485ErrorLimit1") == (96, None)
    assert where("aio_left", "O_1") == (170, 0)
    image = make_image(tmp_path)  # a real idle image: RS485 limits 0, not piCtory's 10/1000
    hal = RevPiHal(IoMap(), image, path("aio_left"))
    hal.close()
    assert Path(image).read_bytes() == bytes(IMAGE_BYTES)  # nothing was ever written


def test_a_compact_runs_a_whole_session_on_bits_of_its_bytes(tmp_path: Path) -> None:
    ride = RevPiRide(tmp_path, COMPACT, path("compact"))
    lamp = where("compact", "DOut.6")
    try:
        set_bit(ride.image, *lamp, True)  # a lamp another program drives on the same byte
        ride.step()
        assert ride.state is not MachineState.FAULT_ESTOP  # the E-stop bit reads released
        for command in (Command.CALIBRATE_TILT, Command.CALIBRATE_ROTATE):
            assert ride.send(command).success
            ride.run_until(lambda: ride.state is not MachineState.CALIBRATING)
        assert ride.send(Command.HOME).success
        ride.run_until(lambda: ride.state is not MachineState.HOMING)
        assert ride.send(Command.START).success
        ride.run_until(lambda: ride.state in (MachineState.DONE, MachineState.FAULT_HW))
        assert ride.state is MachineState.DONE, ride.state_machine.fault
        assert ride.sim.world.tilt_deg == pytest.approx(45.0, abs=ride.config.tilt.tolerance_deg)
        assert Path(ride.image).read_bytes()[lamp[0]] == 1 << 6  # relays off, the lamp still on
    finally:
        ride.close()


# -- tiltPosition must be a 16-bit analog word; digital IOs are bits ------------------------
def tilt(channel: str, words: str, layout: str = "aio_left") -> tuple[str, str, str, str]:
    """A case of `tiltPosition` mapped to `channel`, whose refusal says `words`."""
    return (layout, "tiltPosition", channel, words)


@pytest.mark.parametrize(
    ("layout", "field", "channel", "words"),
    [
        tilt("RevPiStatus", "an 8-bit input byte of module 'core' (RevPi Core)"),
        tilt("Counter_1", "a 32-bit input value of module 'dio' (DIO)"),
        tilt("Input_1", "an 8-bit input byte of module 'pn' (gateway)", layout="gateway"),
        tilt("Status", "a status word of module 'dio' (DIO)"),
        tilt("RS485ErrorCnt", "a status word of module 'core' (RevPi Core)"),
        tilt("Status", "a status word of module 'di' (DI)", layout="connect4_ro"),
        tilt("InputStatus_1", "an 8-bit input byte of module 'aio_left' (AIO)"),
        tilt("OutputValue_1", "a 16-bit output word"),
        tilt("InputValue_1.0", "one bit; an analog value is a whole word"),
        ("compact", "estop", "DIn_i01.8", "has 8 bits (0..7), so it has no bit 8"),
        ("compact", "estop", "DOut.1", "output byte"),
        ("compact", "rotateRelay", "DIn_i01.3", "input byte"),
        ("aio_left", "estop", "I_3.0", "a single bit already: map it as 'I_3'"),
    ],
)
def test_an_io_of_the_wrong_kind_is_refused(
    tmp_path: Path, layout: str, field: str, channel: str, words: str
) -> None:
    base = WORKING.get(layout, IoMap())
    iomap = IoMap.model_validate({**base.model_dump(by_alias=True), field: channel})
    findings = check_revpi_io(iomap, path(layout), make_image(tmp_path))
    assert errors(findings) == [("io_type", f"/hal/iomap/{field}")]
    bad = next(f for f in findings if f.severity is Severity.ERROR)
    assert words in bad.message
    if field == "tiltPosition":
        assert "16-bit input word" in bad.message


def test_missing_tilt_position_lists_the_analog_words_renamed_first(tmp_path: Path) -> None:
    iomap = RENAMED.model_copy(update={"tilt_position": "InputValue_1"})
    findings = check_revpi_io(iomap, path("renamed"), make_image(tmp_path))
    assert errors(findings) == [("io_missing", "/hal/iomap/tiltPosition")]
    message = findings[0].message
    candidates = message.split("candidates: ")[1].split(", ")
    assert candidates[:2] == ["tilt_pos", "seat_load"]
    for status in ("RevPiStatus", "RS485ErrorCnt", "Status", "Counter_1", "Core_Temperatur"):
        assert status not in candidates


def test_no_analog_module_says_to_add_one(tmp_path: Path) -> None:
    findings = check_revpi_io(IoMap(), path("gateway"), make_image(tmp_path))
    assert errors(findings) == [("io_missing", "/hal/iomap/tiltPosition")]
    assert "no analog input word at all: add an AIO" in findings[0].message


# -- Compact and Flat: digital IO as whole bytes ----------------------------------------------
def test_a_compact_byte_mapped_as_a_digital_io_says_how_to_map_a_bit(tmp_path: Path) -> None:
    iomap = COMPACT.model_copy(update={"estop": "DIn_i01", "tilt_relay": "DOut"})
    findings = check_revpi_io(iomap, path("compact"), make_image(tmp_path))
    assert errors(findings) == [
        ("io_type", "/hal/iomap/estop"),
        ("io_type", "/hal/iomap/tiltRelay"),
    ]
    for f, name in zip(findings, ("DIn_i01", "DOut"), strict=False):
        assert "carries its digital IO as whole bytes" in f.message
        assert f"'{name}.N' with N = 0..7, e.g. '{name}.0'" in f.message


def test_the_compact_default_map_lists_bit_candidates(tmp_path: Path) -> None:
    findings = check_revpi_io(IoMap(), path("compact"), make_image(tmp_path))
    estop = next(f for f in findings if f.path == "/hal/iomap/estop")
    assert "candidates: DIn_i01.0..7" in estop.message
    assert "map one bit as 'NAME.N', e.g. 'DIn_i01.0'" in estop.message
    assert "Status" not in estop.message.split("candidates")[1]


# -- broken layouts: one clear error each, and the HAL touches nothing ------------------------
def refuses_untouched(layout: str, tmp_path: Path) -> list[Finding]:
    image = random_image(tmp_path, seed=7)
    before = Path(image).read_bytes()
    with pytest.raises(RevPiConfigError) as exc:
        RevPiHal(IoMap(), image, path(layout))
    assert Path(image).read_bytes() == before
    return exc.value.findings


def test_fractional_offset_says_what_happened_and_how_to_fix_it(tmp_path: Path) -> None:
    findings = refuses_untouched("fractional", tmp_path)
    assert errors(findings) == [
        ("revpi_layout", "/hal/revpi/configrsc"),
        ("io_missing", "/hal/iomap/tiltPosition"),
    ]
    layout, missing = findings
    assert "fractional offset 123.5, a known piCtory 2.1.2 bug" in layout.message
    assert "revpimodio2 ignores such a module with all its IOs" in layout.message
    assert 'set its "offset" to 124' in layout.message
    assert "on module 'aio' (AIO, position 33)" in missing.message
    assert "no IO of that name" not in missing.message
    fixed = load(Path(path("fractional")))
    fixed["Devices"][2]["offset"] = 124  # the fix the finding names
    assert (
        errors(check_revpi_io(IoMap(), write_config(tmp_path, fixed), make_image(tmp_path))) == []
    )


def test_overlapping_modules_are_one_error_not_dozens_of_warnings(tmp_path: Path) -> None:
    findings = refuses_untouched("overlap", tmp_path)
    assert errors(findings)[0] == ("revpi_layout", "/hal/revpi/configrsc")
    assert "overlap at bytes 100–123" in findings[0].message
    assert "'aio' must start at byte 124 or later" in findings[0].message
    notes = check_revpi_io(IoMap(), path("overlap"), make_image(tmp_path))
    assert sum(f.category == "revpi_config" for f in notes) == 1


def test_a_module_past_the_image_is_a_clear_error(tmp_path: Path) -> None:
    findings = refuses_untouched("past_image", tmp_path)
    assert errors(findings) == [("revpi_layout", "/hal/revpi/configrsc")]
    message = findings[0].message
    assert "past the end of the 4096-byte process image" in message
    assert "byte 124" in message
    assert "KeyError" not in message and "5000" in message


def test_an_io_name_used_twice_is_a_clear_error(tmp_path: Path) -> None:
    data = load(Path(path("aio_left")))
    data["Devices"][0]["inp"]["4"][0] = "I_7"  # an AIO input renamed like a DIO input
    findings = check_revpi_io(IoMap(), write_config(tmp_path, data), make_image(tmp_path))
    assert ("revpi_layout", "/hal/revpi/configrsc") in errors(findings)
    assert any("'I_7' is used on module 'aio_left'" in f.message for f in findings)


# -- a relay module shared with other signals ---------------------------------------------------
def test_validation_names_the_outputs_that_share_our_byte_and_module(tmp_path: Path) -> None:
    findings = check_revpi_io(IoMap(), path("shared_dio"), make_image(tmp_path))
    shared = [f for f in findings if f.category == "io_shared"]
    assert len(shared) == 1 and shared[0].severity is Severity.WARNING
    assert (
        "conv_run, conv_dir, lamp, O_8 share byte 81 with O_1, O_2, O_3, O_4" in shared[0].message
    )
    assert "never writes O_9" in shared[0].message and "PWM_16" in shared[0].message
    default = [f for f in findings if f.category == "io_default"]
    assert [f.path for f in default] == ["/hal/iomap/rotateDir"]  # our O_2; lamp is not ours


@pytest.mark.hazard("H48")
def test_other_signals_on_the_relay_module_keep_their_values(tmp_path: Path) -> None:
    image = make_image(tmp_path)
    set_bit(image, *where("shared_dio", "conv_run"), True)  # the conveyor runs
    # lamp (default 1) is off and fan_pwm (default 40) is 0: nobody forces their defaults.
    hal = RevPiHal(IoMap(), image, path("shared_dio"))
    relays = where("shared_dio", "O_1")[0]
    try:
        assert Path(image).read_bytes()[relays] == 0b0001_0000
        hal.scan_outputs(Outputs(ro={"O_1": True, "O_4": True}))
        assert Path(image).read_bytes()[relays] == 0b0001_1001
        set_bit(image, *where("shared_dio", "conv_dir"), True)  # the other program reverses
        hal.scan_outputs(Outputs(ro={"O_1": True}))
        assert Path(image).read_bytes()[relays] == 0b0011_0001
        hal.force_all_outputs_safe()
        assert Path(image).read_bytes()[relays] == 0b0011_0000
    finally:
        hal.close()
    data = Path(image).read_bytes()
    assert data[relays] == 0b0011_0000
    assert data[where("shared_dio", "fan_pwm")[0]] == 0


def test_corpus_json_is_piCtory_shaped() -> None:
    for name in LAYOUTS:
        doc = json.loads(Path(path(name)).read_text(encoding="utf-8"))
        assert set(doc) >= {"App", "Summary", "Devices"}
        for dev in doc["Devices"]:
            assert {"type", "productType", "position", "name", "offset"} <= set(dev)
