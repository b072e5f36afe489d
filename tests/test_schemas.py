"""specs/schemas holds exactly what the code validates with; the examples of the seed fit it."""

from __future__ import annotations

import json
from pathlib import Path

from arena.schemas import schemas

SPEC_DIR = Path(__file__).resolve().parent.parent / "specs" / "schemas"


def test_spec_schemas_match_the_code() -> None:
    expected = schemas()
    on_disk = {p.name: p.read_text(encoding="utf-8") for p in SPEC_DIR.glob("*.json")}
    assert sorted(on_disk) == sorted(expected), "run `arena schemas` to regenerate specs/schemas"
    for name, text in expected.items():
        assert on_disk[name] == text, f"{name} is stale: run `arena schemas`"


def test_master_schema_names_every_master_message_type() -> None:
    schema = json.loads((SPEC_DIR / "master-message.json").read_text())
    tags = {
        definition["properties"]["type"]["enum"][0]
        for definition in schema["$defs"].values()
        if "type" in definition.get("properties", {}) and "enum" in definition["properties"]["type"]
    }
    assert {"command", "sequence", "heartbeat", "estop", "reset"} <= tags
