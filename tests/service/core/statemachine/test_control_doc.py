"""The README's state table and docs/states.md are what the transition table generates."""

from __future__ import annotations

from pathlib import Path

import pytest

from ride_machine.schema.commands import Command
from ride_machine.schema.status import MachineState
from ride_machine.service.core.statemachine import Occurrence, control_doc


def test_readme_and_states_page_match_the_transition_table() -> None:
    for path, text in control_doc.outputs().items():
        assert path.read_text() == text, (
            f"{path.name} is stale: run"
            " `python -m ride_machine.service.core.statemachine.control_doc`"
        )


def test_check_reports_a_stale_file_and_the_generator_fixes_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    readme, page = tmp_path / "README.md", tmp_path / "docs" / "states.md"
    page.parent.mkdir()
    readme.write_text(control_doc.README.read_text().replace("`RESP_PAUSED`", "`RESP_NAPPING`"))
    page.write_text(control_doc.states_md())
    monkeypatch.setattr(control_doc, "ROOT", tmp_path)
    monkeypatch.setattr(control_doc, "README", readme)
    monkeypatch.setattr(control_doc, "STATES_MD", page)

    assert control_doc.main(["--check"]) == 1
    assert "README.md is stale" in capsys.readouterr().out
    assert control_doc.main([]) == 0
    assert control_doc.main(["--check"]) == 0
    assert "`RESP_PAUSED`" in readme.read_text()


def test_generated_docs_name_every_state_command_and_event() -> None:
    page = control_doc.states_md()
    diagram = control_doc.mermaid()
    for state in MachineState:
        assert f" {state} -->" in diagram or f"--> {state}:" in diagram, state
    for command in Command:
        assert f"`{command.key}`" in control_doc.command_table()
        assert command.value in diagram
    for event in Occurrence:
        assert f"| {event} |" in page
