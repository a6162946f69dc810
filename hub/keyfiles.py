"""Key folders on disk: making them (``khepri keys init``, ``keys add``) and reading them (the hub's keyring,
``khepri ctl``'s operator pair). Authentication with them is ``hub/security.py``.

Key folder (``khepri keys init DIR``)::

    DIR/hub.key, DIR/hub.key_secret                     the hub's pair (the secret stays on the lab PC)
    DIR/robots/robot-<id>.key, robot-<id>.key_secret    one pair per robot; copy both + hub.key to the robot
    DIR/operators/<name>.key, <name>.key_secret         one pair per operator (khepri ctl)
"""
from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

import zmq
import zmq.auth

from onboard.agent.link import exposed_secret, key_folder_problem
from onboard.config import ConfigError

ROBOT_KEY = re.compile(r"^robot-(\d+)\.key$")
MAX_OPERATOR_NAME = 64
HUB_KEYS_FIELD = "security.keys"   # what the hub's key errors name: the lab config's key


@dataclass
class KeyRing:
    """What the hub needs: its own pair and the public keys it accepts (z85 bytes -> identity)."""

    folder: Path
    public: bytes
    secret: bytes
    robots: Dict[bytes, int] = field(default_factory=dict)
    operators: Dict[bytes, str] = field(default_factory=dict)


def init_keys(folder: Path, robot_ids: List[int], operators: List[str], force: bool = False) -> List[Path]:
    """Create the hub, robot and operator key pairs. Refuses to overwrite existing keys unless ``force``; with
    it, the folder holds exactly the new set afterwards (``stale_keys`` names what ``force`` removes)."""
    targets = [folder / "hub.key"] + _peer_keys(folder, robot_ids, operators)
    _refuse_files_in_the_way(folder, targets)
    # Secrets too: a hub.key_secret alone (its hub.key lost or not yet copied back) was replaced without a word,
    # and every robot given the old hub.key could no longer reach the hub.
    files = [path for target in targets for path in (target, target.with_suffix(".key_secret"))]
    existing = [path for path in files if path.exists() or path.is_symlink()]
    if existing and not force:
        raise ConfigError("FOLDER", f"{existing[0]} already exists (use --force to replace keys)")
    check_operator_names(operators)
    for path in stale_keys(folder, targets) if force else []:   # rotating keys must not leave an old robot
        path.unlink()                                             # or operator key that the hub still accepts
    return _create_pairs(targets)


def add_keys(folder: Path, robot_ids: List[int], operators: List[str]) -> List[Path]:
    """Add robot and operator key pairs to an existing key folder, leaving every key in it as it is (the hub's
    and the other robots' and operators'), so nothing already given out has to be copied again. Refuses a
    robot or operator that already has a key: replacing one is deleting it first, or ``init --force``. A
    revoked key's leftover secret (``revoked_secrets``) is replaced."""
    if not (folder / "hub.key").is_file():
        raise ConfigError("FOLDER", f"no hub key {folder / 'hub.key'}: make the lab's keys with "
                                    f"`khepri keys init {folder}` first")
    # The new robots are told to take hub.key with them: one damaged was handed out, and refused only later, by
    # the hub and by every agent.
    _certificate(folder / "hub.key", "FOLDER")
    check_operator_names(operators)
    targets = _peer_keys(folder, robot_ids, operators)
    _refuse_files_in_the_way(folder, targets)
    for path in targets:
        _refuse_a_key_in_use(path)
    return _create_pairs(targets)


def revoked_secrets(folder: Path, robot_ids: List[int], operators: List[str]) -> List[Path]:
    """The secret files these robots and operators still have without their public key: what revoking a key
    (deleting its ``.key``) leaves behind. ``add_keys`` replaces them; the hub no longer accepts them anyway."""
    secrets = [path.with_suffix(".key_secret") for path in _peer_keys(folder, robot_ids, operators)]
    return [path for path in secrets if path.exists() and not path.with_suffix(".key").exists()]


def _peer_keys(folder: Path, robot_ids: List[int], operators: List[str]) -> List[Path]:
    return [peer_key_path(folder, "robot", i) for i in robot_ids] \
        + [peer_key_path(folder, "operator", name) for name in operators]


def peer_key_path(folder: Path, kind: str, who: Any) -> Path:
    """Where the public key of robot ``who`` (``kind`` "robot") or operator ``who`` lies in a key folder."""
    return folder / "robots" / f"robot-{who}.key" if kind == "robot" else folder / "operators" / f"{who}.key"


def _refuse_a_key_in_use(path: Path) -> None:
    """A robot or operator whose public key is in the folder keeps it (the hub accepts it, and the robot may hold
    its secret): replacing it is deleting it first. The hint names only the files that are there."""
    if not path.exists():
        return
    robot = path.parent.name == "robots"
    who = f"robot {path.stem[len('robot-'):]}" if robot else f"operator {path.stem}"
    secret = path.with_suffix(".key_secret")
    files = f"{path.name} and {secret.name}" if secret.exists() else path.name
    raise ConfigError("--robots" if robot else "--operator",
                      f"{who} already has a key ({path}); to replace it, delete {files} first")


def _refuse_files_in_the_way(folder: Path, targets: List[Path]) -> None:
    """A file where the key folder or its robots/ or operators/ folder goes, checked before anything is written:
    found half-way, the hub's pair was already made, and running init again was refused for it."""
    for place in dict.fromkeys([folder] + [path.parent for path in targets]):
        if place.exists() and not place.is_dir():
            raise ConfigError("FOLDER", f"{place} is a file, not a folder: move it away first")


def _create_pairs(targets: List[Path]) -> List[Path]:
    """The pairs, made under a private umask: the secret was written with the umask's mode and then made 0600,
    and under umask 000 the folders and public keys came out writable by everyone (who could swap a key)."""
    created = []
    previous = os.umask(0o077)
    try:
        for path in targets:
            path.parent.mkdir(parents=True, exist_ok=True)
            public, secret = zmq.auth.create_certificates(str(path.parent), path.stem)
            Path(public).chmod(0o644)        # readable: the robots and operators are given copies
            Path(secret).chmod(0o600)
            created += [Path(public), Path(secret)]
    finally:
        os.umask(previous)
    folders = {path.parent for path in targets} | {path.parent.parent for path in targets if path.name != "hub.key"}
    for folder in folders:
        mode = folder.stat().st_mode & 0o777
        if mode & 0o022:            # the key folder made beforehand, under the caller's umask
            folder.chmod(mode & ~0o022)
    return created


def check_operator_names(operators: List[str]) -> None:
    """An operator name becomes a file name: refuse one that would not be a plain one."""
    for name in operators:
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
            raise ConfigError("--operator", f"use letters, digits, '.', '_' or '-' only (got {name!r})")
        if name[0] in ".-":     # `.`/`..` made `...key`; `-x` cannot be given back to `ctl --operator`
            raise ConfigError("--operator", f"must start with a letter, a digit or '_' (got {name!r})")
        if len(name) > MAX_OPERATOR_NAME:     # its .key_secret must fit a file name (checked before writing)
            raise ConfigError("--operator", f"at most {MAX_OPERATOR_NAME} characters (got {len(name)})")


def stale_keys(folder: Path, keep: List[Path]) -> List[Path]:
    """Robot and operator key files in ``folder`` (public and secret) whose pair is not among ``keep``."""
    kept = {path.with_suffix("") for path in keep}
    found = list((folder / "robots").glob("robot-*.key*")) + list((folder / "operators").glob("*.key*"))
    return sorted(path for path in found
                  if path.suffix in (".key", ".key_secret") and path.with_suffix("") not in kept)


def load_keyring(folder: Path, need_robots: bool = True) -> KeyRing:
    """The hub's pair and the keys it accepts. ``need_robots``: at start a folder without robot keys is an error;
    re-read while the hub runs (``hub/key_reload.py``), it means every robot key was revoked."""
    problem = key_folder_problem(folder)
    if problem:
        raise ConfigError(HUB_KEYS_FIELD, problem)
    public, secret = _load_pair(folder / "hub.key_secret", "hub", HUB_KEYS_FIELD)
    if load_public(folder / "hub.key", HUB_KEYS_FIELD) != public:
        # What robots and operators are given: with another key there, every client is refused, and each
        # was told its hub.key was not this hub's (it was this folder's hub.key).
        raise ConfigError(HUB_KEYS_FIELD, f"{folder / 'hub.key'} is not the public key of {folder / 'hub.key_secret'} "
                                          "(copied from another key folder?): robots and operators given it could "
                                          "not connect; copy the pair from one `khepri keys init`")
    ring = KeyRing(folder, public, secret)
    holders: Dict[bytes, Path] = {public: folder / "hub.key"}
    for path in sorted((folder / "robots").glob("robot-*.key")):
        match = ROBOT_KEY.match(path.name)
        if match:
            ring.robots[_unique_public(path, holders)] = int(match.group(1))
    for path in sorted((folder / "operators").glob("*.key")):
        ring.operators[_unique_public(path, holders)] = path.stem
    if need_robots and not ring.robots:
        raise ConfigError(HUB_KEYS_FIELD, f"no robot keys in {folder / 'robots'} (add them with `khepri keys add "
                                          f"{folder} --robots N`)")
    return ring


def operator_client_keys(folder: Path, name: Optional[str] = None) -> Dict[str, bytes]:
    """``khepri ctl``'s side: an operator pair (the only one in the folder unless ``name`` is given)."""
    problem = key_folder_problem(folder)
    if problem:
        raise ConfigError("--keys", problem)
    found = sorted((folder / "operators").glob("*.key_secret"))
    candidates = [p for p in found if name is None or p.stem == name]
    stem = name.rsplit(".", 1)[0] if name is not None and name.endswith((".key_secret", ".key")) else None
    if not candidates and any(p.stem == stem for p in found):
        raise ConfigError("--operator", f"takes the operator's name, not its key file: --operator {stem}")
    if not candidates:
        # With keys in the folder, the name is what is wrong (`--operator bob` among alice's): say that option.
        option = "--operator" if name is not None and found else "--keys"
        raise ConfigError(option, f"no operator key{'' if name is None else ' ' + repr(name)} in "
                                  f"{folder / 'operators'}{' (it holds ' + key_files(found) + ')' if found else ''}")
    if len(candidates) > 1:
        raise ConfigError("--operator", f"several operator keys in {folder / 'operators'}: {key_files(found)}; "
                                        f"name one, e.g. --operator {found[0].stem}")
    public, secret = _load_pair(candidates[0], "operator", "--keys")
    exposed = exposed_secret(candidates[0])
    if exposed:
        print(f"khepri ctl: warning: {exposed}", file=sys.stderr, flush=True)
    return {"public": public, "secret": secret, "server": load_public(folder / "hub.key", "--keys")}


def key_files(paths: List[Path]) -> str:
    """'alice.key_secret, bob.key_secret': the key files an error offers to choose from."""
    return ", ".join(path.name for path in paths)


def _certificate(path: Path, where: str):
    """``zmq.auth.load_certificate``, its errors said as the key's: one this user may not read was called "not a
    key file", or said without the field at all (a folder it may not enter)."""
    try:
        return zmq.auth.load_certificate(str(path))
    except PermissionError:
        raise ConfigError(where, f"{path}: this user may not read it (permission denied): run as the user that "
                                 "made the keys, or give this one read access") from None
    except (OSError, ValueError) as err:
        raise ConfigError(where, f"{path}: not a key file ({err})") from None


def _is_file(path: Path, where: str) -> bool:
    try:
        return path.is_file()
    except PermissionError:
        raise ConfigError(where, f"{path.parent}: this user may not enter the folder (permission denied): run as "
                                 "the user that made the keys, or give this one access") from None


def _load_pair(path: Path, who: str, where: str):
    """``where``: what the error names, the hub config's ``security.keys`` or ``khepri ctl --keys``."""
    if not _is_file(path, where):
        raise ConfigError(where, f"no {who} key {path} (run `khepri keys init {path.parent}`, or --insecure "
                          "on a trusted loopback only)")
    public, secret = _certificate(path, where)
    if secret is None:
        raise ConfigError(where, f"{path}: holds no secret key")
    try:
        derived = zmq.curve_public(secret)
    except (zmq.ZMQError, ValueError):
        raise ConfigError(where, f"{path}: its secret key is not a CURVE key") from None
    if derived != public:      # an edited file: the clients would be told the wrong public key
        raise ConfigError(where, f"{path}: its public key is not its secret key's pair (an edited file? make the "
                                 f"keys again with `khepri keys init --force`)")
    return public, secret


def _unique_public(path: Path, holders: Dict[bytes, Path]) -> bytes:
    """A public key of the hub's folder that no other file of it holds: a copied key file would make one
    peer two (robot-1.key copied to robot-9.key: the later file won, and robot 1 was refused as robot 9)."""
    public = load_public(path, HUB_KEYS_FIELD)
    if public in holders:
        raise ConfigError(HUB_KEYS_FIELD, f"{holders[public]} and {path} hold the same key: each robot and "
                                          f"operator needs its own pair (delete the copy)")
    holders[public] = path
    return public


def load_public(path: Path, where: str) -> bytes:
    if not _is_file(path, where):
        raise ConfigError(where, f"no public key {path}" + (" (a folder)" if path.is_dir() else ""))
    return _certificate(path, where)[0]


def writable_by_others(folder: Path) -> Optional[str]:
    """A warning when others than the owner may write where the hub reads the keys it accepts: whoever can
    add or swap a public key in robots/ or operators/ is let in (the hub re-reads them while it runs). None when private
    (or on a system without POSIX modes)."""
    if os.name != "posix":
        return None
    places = [folder, folder / "robots", folder / "operators", folder / "hub.key"]
    places += sorted((folder / "robots").glob("*.key")) + sorted((folder / "operators").glob("*.key"))
    for place in places:
        try:
            mode = place.stat().st_mode & 0o777
        except OSError:
            continue
        if mode & 0o022:
            return (f"{place} can be written by other users (mode {mode:04o}): anyone who can write there can add "
                    f"or swap a key this hub accepts; run `chmod go-w {place}`")
    return None
