"""``khepri keys init`` and ``khepri keys add``: the CURVE key folder of a lab (hub/keyfiles.py makes it)."""
from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import List

from onboard.config import ConfigError
from onboard.protocol import MAX_ROBOT_ID

from .parsing import command_group


def add_keys_commands(groups) -> None:
    commands = command_group(groups, "keys", "CURVE key pairs for the hub, robots and operators",
                             "Manage the lab's CURVE keys (see docs/lab.md).")
    init = commands.add_parser("init", help="create hub, robot and operator key pairs",
                               description="Create FOLDER/hub.key(_secret), FOLDER/robots/robot-<id>.key(_secret) and "
                                           "FOLDER/operators/<name>.key(_secret).")
    init.add_argument("folder", nargs="?", default="keys", metavar="FOLDER",
                      help="key folder (default ./keys)")
    init.add_argument("--robots", default="6", help="robot count N (ids 0..N-1), or ids with commas: 0,1,5 "
                                                     "(one id: 5,) (default 6)")
    init.add_argument("--operator", action="append", help="operator name (repeatable; default: operator)")
    init.add_argument("--force", action="store_true",
                      help="replace existing keys; robot and operator keys not named again are removed")
    init.set_defaults(func=cmd_keys_init)
    add = commands.add_parser("add", help="add robot or operator key pairs to an existing key folder",
                              description="Add FOLDER/robots/robot-<id>.key(_secret) and FOLDER/operators/<name>.key"
                                          "(_secret) for new robots or operators. Every key already in FOLDER stays "
                                          "as it is; a running hub accepts the new ones from their first connection.")
    add.add_argument("folder", nargs="?", default="keys", metavar="FOLDER",
                     help="key folder (default ./keys)")
    add.add_argument("--robots", help="ids with commas: 6,7 (one id: 6,), or a count N (ids 0..N-1)")
    add.add_argument("--operator", action="append", help="operator name (repeatable)")
    add.set_defaults(func=cmd_keys_add)


def cmd_keys_init(args: argparse.Namespace) -> int:
    from hub.keyfiles import check_operator_names, init_keys, stale_keys
    from khepri_cli.sim_commands import out_folder_problem

    args.folder = key_folder(args.folder)
    ids = parse_robot_ids(args.robots)
    operators = list(dict.fromkeys(args.operator or ["operator"]))     # --operator alice twice: one key pair
    check_operator_names(operators)           # before the folder is made: a refused name leaves nothing behind
    problem = out_folder_problem(args.folder)     # an unwritable place: said with the argument, not the OS error
    if problem:
        raise ConfigError("FOLDER", problem)
    wanted = [args.folder / "robots" / f"robot-{i}.key" for i in ids] \
        + [args.folder / "operators" / f"{name}.key" for name in operators]
    stale = stale_keys(args.folder, wanted) if args.force and args.folder.is_dir() else []
    created = init_keys(args.folder, ids, operators, force=args.force)
    if stale:
        print(f"removed {len(stale)} old key files (the hub would have gone on accepting them): "
              + ", ".join(sorted({path.stem for path in stale})))
    print(f"created {len(created)} key files in {args.folder}: hub, robots {describe_ids(ids)} "
          f"({len(ids)}), operators {', '.join(operators)}")
    print(f"  give robot N: {args.folder}/robots/robot-N.key_secret and {args.folder}/hub.key")
    print(f"  keep secret:  {args.folder}/hub.key_secret, {args.folder}/operators/*.key_secret")
    return 0


def cmd_keys_add(args: argparse.Namespace) -> int:
    from hub.keyfiles import add_keys, revoked_secrets

    args.folder = key_folder(args.folder)
    if args.robots is None and not args.operator:
        raise ConfigError("--robots", "name the robots (--robots 6,7) or operators (--operator NAME) to add")
    ids = parse_robot_ids(args.robots) if args.robots is not None else []
    operators = list(dict.fromkeys(args.operator or []))
    revoked = revoked_secrets(args.folder, ids, operators)
    created = add_keys(args.folder, ids, operators)
    if revoked:
        print(f"replaced what revoked keys had left (a .key_secret without its .key): "
              f"{', '.join(str(path) for path in revoked)}")
    what = ([f"robots {describe_ids(ids)} ({len(ids)})"] if ids else []) \
        + ([f"operators {', '.join(operators)}"] if operators else [])
    print(f"added {len(created)} key files in {args.folder}: {'; '.join(what)}; every other key is unchanged")
    if ids:
        print(f"  give robot N: {args.folder}/robots/robot-N.key_secret and {args.folder}/hub.key")
    print("  a hub using this folder accepts them from now on, running or not")
    return 0


def key_folder(text: str) -> Path:
    """FOLDER of ``keys init|add``. Empty (``khepri keys init "$KEYS"`` with KEYS unset) is refused, as --hub ""
    is: Path("") is the current folder, where the keys would have landed without a word."""
    if not text.strip():
        raise ConfigError("FOLDER", "is empty (an unset shell variable?): name the key folder, e.g. keys")
    return Path(text)


def describe_ids(ids: List[int]) -> str:
    """``0..5`` for a run of ids, else the ids (the first ten)."""
    if len(ids) > 1 and ids == list(range(ids[0], ids[-1] + 1)):
        return f"{ids[0]}..{ids[-1]}"
    return ", ".join(map(str, ids[:10])) + (", ..." if len(ids) > 10 else "")


MAX_KEYED_ROBOTS = 10_000     # a key pair is two files: beyond this a typo, not a lab


def parse_robot_ids(text: str) -> List[int]:
    """``--robots``: a count N (ids 0..N-1) or a list of ids like ``0,1,5``."""
    parts = [part.strip() for part in text.split(",")]
    if len(parts) > 1 and not parts[-1]:
        parts.pop()         # `5,`: a list of one id
    # ASCII digits only: int() reads '٣' as 3, and `3,,4` lost an id typed between the commas.
    if not all(re.fullmatch(r"-?[0-9]+", part) for part in parts):
        raise ConfigError("--robots", f"give a count like 6 or ids like 0,1,5 (got {text!r})")
    numbers = [int(part) for part in parts]
    if "," not in text and numbers:
        if numbers[0] == 0:     # a count of none: most likely robot 0 was meant
            raise ConfigError("--robots", "0 is a count of no robots (a single number is a count N: ids 0..N-1); "
                                          "for robot id 0 alone, give --robots 0, (a list of one id)")
        return list(range(check_robot_count(numbers[0])))
    twice = next((i for k, i in enumerate(numbers) if i in numbers[:k]), None)
    if twice is not None:       # `1,1` is more likely a typo for `1,2` than a wish for robot 1 once
        raise ConfigError("--robots", f"lists robot {twice} twice (got {text!r})")
    ids = sorted(numbers)
    if not ids:
        raise ConfigError("--robots", f"give at least one robot id (got {text!r})")
    bad = [i for i in ids if not 0 <= i <= MAX_ROBOT_ID]
    if bad:
        raise ConfigError("--robots", f"robot ids must be 0..{MAX_ROBOT_ID} (got {bad[0]})")
    check_robot_count(len(ids))
    return ids


def check_robot_count(count: int) -> int:
    if count < 1:
        raise ConfigError("--robots", f"the robot count must be >= 1 (got {count})")
    if count > MAX_KEYED_ROBOTS:
        raise ConfigError("--robots", f"at most {MAX_KEYED_ROBOTS} robots (got {count})")
    return count
