"""Sub-commands (see edge/cli.py). Keep heavy imports inside the command functions."""
from __future__ import annotations


def register(sub) -> None:
    """Add this module's sub-commands to the argparse sub-parsers."""
