"""``acm-rs gapfill`` and ``acm-rs gapfill-eval`` subcommands."""

from __future__ import annotations

import argparse


def add_subcommands(sub: argparse._SubParsersAction) -> None:
    """Register the gap-filling subcommands on the ``acm-rs`` parser."""
