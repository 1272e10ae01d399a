"""The ``equidiff`` subcommands, one module each (``add_arguments`` + ``run``), and the options they share."""

from __future__ import annotations

import argparse

FORCE_HELP = "replace an existing output (only once the new one is complete; without it an existing one is refused)"


def add_force_argument(parser: argparse.ArgumentParser, help: str = FORCE_HELP) -> None:
    """``--force``: every command that writes refuses an existing output (``OutputExistsError``) without it."""
    parser.add_argument("--force", action="store_true", help=help)
