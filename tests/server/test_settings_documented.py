"""Every field of the service's settings has a row in docs/api.md's settings table, and every row
names a field: deployment.md sends operators there for the whole list."""

from __future__ import annotations

import re
from pathlib import Path

from server.settings import Settings

API_MD = Path(__file__).resolve().parents[2] / "docs" / "api.md"


def documented_settings(text: str) -> set[str]:
    """The variables named in the first cell of the rows of the table under ``## Settings``."""
    section = text.split("\n## Settings\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| `CANONICAL_")]
    return {name for row in rows for name in re.findall(r"`(CANONICAL_[A-Z0-9_]+)`", row.split("|")[1])}


def test_every_setting_has_a_row_in_the_api_settings_table():
    fields = {f"CANONICAL_{name.upper()}" for name in Settings.model_fields}
    documented = documented_settings(API_MD.read_text())
    assert not fields - documented, f"settings without a row in docs/api.md#settings: {sorted(fields - documented)}"
    assert not documented - fields, f"rows of docs/api.md#settings that are no setting: {sorted(documented - fields)}"
