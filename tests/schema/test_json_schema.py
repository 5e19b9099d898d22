"""The checked-in JSON Schema (schema/json/) is what the models generate, and the key table is
complete. (The Node/ajv check against a live daemon is tests/integration/test_schema_node.py.)"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

from ride_machine.schema.commands import Command
from ride_machine.schema.jsonschema import DIALECT, documents, render
from ride_machine.schema.keys import KEYS, Direction, markdown_table, match
from tests.procs import REPO, machine_cmd

CHECKED_IN = REPO / "schema" / "json"


def machine_schema(directory: Path) -> subprocess.CompletedProcess[str]:
    """`machine schema DIRECTORY`, as a user runs it."""
    return subprocess.run(
        machine_cmd("schema", str(directory)),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        cwd=REPO,
    )


def test_checked_in_schema_matches_the_models() -> None:
    docs = documents()
    on_disk = {p.name for p in CHECKED_IN.glob("*.json")}
    assert on_disk == set(docs), "run `machine schema` and commit schema/json/"
    for name, doc in docs.items():
        assert (CHECKED_IN / name).read_text() == render(doc), (
            f"schema/json/{name} is stale: run `machine schema` and commit it"
        )


def test_machine_schema_writes_the_same_files(tmp_path: Path) -> None:
    out = tmp_path / "json"
    (tmp_path / "json").mkdir()
    gone = {"$schema": DIALECT, "$id": "Gone.json"}
    (out / "Gone.json").write_text(json.dumps(gone))  # a model that no longer exists is removed
    done = machine_schema(out)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(p.name for p in CHECKED_IN.iterdir())
    for path in out.iterdir():
        assert path.read_text() == (CHECKED_IN / path.name).read_text()


def test_key_table_names_every_command_and_its_models() -> None:
    keys = json.loads((CHECKED_IN / "keys.json").read_text())
    by_key = {k["key"]: k for k in keys["keys"]}
    for command in Command:
        entry = by_key[f"cmd/{command.key}"]
        assert entry["direction"] == "request-reply"
        assert entry["reply"] == "Reply"
        assert (CHECKED_IN / f"{entry['request']}.json").exists()
    assert by_key["cmd/start"]["request"] == "StartRequest"
    assert keys["error_reply"] == "Reply"
    for entry in keys["keys"]:
        for model in (entry["request"], entry["reply"]):
            assert model is None or (CHECKED_IN / f"{model}.json").exists(), entry


def test_concrete_keys_match_their_pattern() -> None:
    assert match("axis/rotate") is not None and match("axis/rotate").key == "axis/<name>"  # type: ignore[union-attr]
    assert match("io/di/estop").key == "io/<kind>/<name>"  # type: ignore[union-attr]
    assert match("cmd/home").key == "cmd/home"  # type: ignore[union-attr]
    assert match("cmd/fly") is None and match("axis") is None
    assert all(spec.direction in Direction for spec in KEYS)
    assert len({spec.key for spec in KEYS}) == len(KEYS)


def test_requests_are_strict_and_replies_are_open() -> None:
    docs = documents()
    assert docs["CommandRequest.json"]["additionalProperties"] is False
    assert "additionalProperties" not in docs["Status.json"]  # old readers skip new fields


def test_docs_hold_the_generated_key_table() -> None:
    text = (REPO / "docs" / "schema.md").read_text()
    start = text.index("-->\n", text.index("<!-- generated from schema/keys.py")) + 4
    end = text.index("<!-- end of generated table -->")
    assert text[start:end] == markdown_table(), "docs/schema.md: paste markdown_table() again"


def test_protocol_key_table_covers_every_key_of_the_table() -> None:
    page = (REPO / "docs" / "protocol.md").read_text()
    section = page[page.index("## Key space") :]
    section = section[: section.index("\n\n", section.index("| key |"))]
    documented = [
        ref
        for row in section.splitlines()
        if row.startswith("| `")
        for ref in re.findall(r"`([^`]+)`", row.split(" | ")[0])
    ]
    # `<command>` stands for a command key, which may have two chunks (`calibrate/tilt`).
    patterns = [re.sub(r"<[^>]+>", "[^/]+", ref.replace("<command>", ".+")) for ref in documented]

    def example(key: str) -> str:
        return re.sub(r"<[^>]+>", "rotate", key.replace("<kind>", "di"))

    for spec in KEYS:
        assert any(re.fullmatch(p, example(spec.key)) for p in patterns), (
            f"docs/protocol.md's key table has no row for {spec.key}"
        )


def test_machine_schema_into_a_directory_of_other_files_leaves_them_alone(tmp_path: Path) -> None:
    theirs = {
        "package.json": '{"name": "app"}',
        "broken.json": "{not json",
        "Other.json": json.dumps({"$schema": DIALECT, "$id": "Renamed.json"}),
    }
    for name, text in theirs.items():
        (tmp_path / name).write_text(text)
    done = machine_schema(tmp_path)
    assert done.returncode == 0, done.stderr
    for name, text in theirs.items():
        assert (tmp_path / name).read_text() == text
    assert (tmp_path / "keys.json").exists()


def test_machine_schema_where_it_cannot_write_is_a_clear_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    for target in (blocker, blocker / "json"):  # a file where the directory goes; below a file
        done = machine_schema(target)
        assert done.returncode == 1
        assert done.stderr.startswith(f"machine: cannot write the schema to {target}: ")
        assert "Traceback" not in done.stderr
