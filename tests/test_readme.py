"""The README tells the truth: its register tables and commands match the code and the YAML."""
from __future__ import annotations

import re
from pathlib import Path

from edge.cli import build_parser
from edge.commands.gateway_cmds import render_markdown
from edge.config import load_config

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")


def test_advisory_table_and_status_bits_match_the_config():
    generated = render_markdown(load_config(REPO / "config" / "gateway.yaml", load_plant=False))
    section = generated[generated.index("## Advisory block"):]
    table_rows = [line for line in section.splitlines() if line.startswith("| ")]
    assert len(table_rows) > 20
    for line in table_rows:
        assert line in README, f"README advisory table differs from the config: {line}"


def test_setup_commands_and_every_documented_command_exists():
    assert "make demo" in README and "make test" in README
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    registered = set(sub.choices)
    documented = set(re.findall(r"`hp-edge ([a-z][a-z-]+)", README))
    assert documented, "README documents no command"
    assert documented <= registered, f"README names unknown commands: {documented - registered}"
    assert registered <= documented, f"commands missing from the README: {registered - documented}"
