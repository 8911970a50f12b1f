"""The controller's protocol document (hardware/PROTOCOL.md) read as tables."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository
PROTOCOL_MD = ROOT / "hardware" / "PROTOCOL.md"


def protocol_table(section: str) -> list[list[str]]:
    """Rows (cells stripped) of the first markdown table under ``## section``."""
    text = PROTOCOL_MD.read_text(encoding="utf-8").split(f"## {section}\n", 1)[1]
    rows = []
    for line in text.splitlines():
        if line.startswith("## "):
            break
        if line.startswith("|") and not set(line) <= set("|- "):
            rows.append([c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]])
    return rows[1:]  # drop the header row
