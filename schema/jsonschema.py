"""JSON Schema of the wire contract, generated from the pydantic models (`machine schema`).

Requests are described as the machine validates them, replies and publications as it
serialises them. One file per model (`<Model>.json`, `$id` the file name) and `keys.json`, the
key space as data, so a client in any language can check what it sends and receives.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ride_machine.schema import SCHEMA_VERSION

from .keys import ERROR_REPLY, KEYS, models

DIALECT = "https://json-schema.org/draft/2020-12/schema"


def documents() -> dict[str, dict[str, Any]]:
    """File name → JSON document, for every model of the key space and the key table."""
    out: dict[str, dict[str, Any]] = {}
    for name, (model, is_request) in sorted(models().items()):
        if is_request:
            body = model.model_json_schema(mode="validation")
        else:
            body = model.model_json_schema(mode="serialization")
        out[f"{name}.json"] = {"$schema": DIALECT, "$id": f"{name}.json", **body}
    out["keys.json"] = {
        "schema_version": SCHEMA_VERSION,
        "prefix": "machine/<id>",
        "error_reply": ERROR_REPLY.__name__,
        "keys": [spec.as_json() for spec in KEYS],
    }
    return out


def render(doc: dict[str, Any]) -> str:
    return json.dumps(doc, indent=2, ensure_ascii=False) + "\n"


def ours(path: Path) -> bool:
    """Whether `path` is a document this module wrote (its `$schema` and `$id`), so that a
    directory given by mistake loses none of its own `*.json` files."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and doc.get("$schema") == DIALECT and doc.get("$id") == path.name


def write(directory: Path) -> list[Path]:
    """Write every document into `directory` (created if needed); stale documents of ours
    (a model that no longer exists) are removed, any other file is left alone."""
    directory.mkdir(parents=True, exist_ok=True)
    docs = documents()
    for old in directory.glob("*.json"):
        if old.name not in docs and ours(old):
            old.unlink()
    paths = []
    for name, doc in docs.items():
        path = directory / name
        path.write_text(render(doc))
        paths.append(path)
    return paths
