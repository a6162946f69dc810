"""What the command modules share in building the command line."""
from __future__ import annotations

import argparse


def command_group(groups, name: str, help_text: str, description: str) -> argparse._SubParsersAction:
    """``khepri NAME SUBCOMMAND``: the group's parser, and its subcommands' (one of them is required)."""
    group = groups.add_parser(name, help=help_text, description=description)
    return group.add_subparsers(dest="command", metavar="SUBCOMMAND", required=True)
