"""The ``khepri`` command: a thin dispatcher over the project's folders. Nothing imports this package."""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional

from onboard.config import ConfigError

from . import sim_commands


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="khepri", description="Swarm behaviours from simulation to KheperaIV robots.")
    groups = parser.add_subparsers(dest="group", metavar="COMMAND", required=True)
    sim_commands.add_sim(groups)
    sim_commands.add_bench(groups)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ConfigError as err:
        print(f"khepri: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("khepri: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
