"""A study's folder (``--out``): its ``study.json``, and whether a study may write into the folder.

A study writes its ``study.json`` before it runs anything (``driver.record_study``), so every folder a study ran
into holds one, unless the command was stopped in the moment between taking the folder's lock and writing it:
such a folder holds only the lock (and perhaps study.json's temporary file), and is resumed as a new one.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Dict, Optional

from onboard.config import ConfigError, as_written
from onboard.jsontext import parse_json

STUDY_FILE = "study.json"
STUDY_TMP = "study.tmp"           # study.json is written here first, then renamed into place
LOCK_FILE = "study.lock"          # flock'ed by the command running the study; holds its pid
UNWRITABLE_KEY = "unwritable"     # study.json: run folder -> why its result.json could not be written
# What a study makes in its folder before its study.json is there: a folder holding nothing else is a new one.
BEFORE_STUDY_JSON = (LOCK_FILE, STUDY_TMP)


def check_out_folder(out: Path, name: str, merge: bool) -> None:
    """Whether study ``name`` may write into ``out``; a one-line ConfigError when not. A folder of other files (no
    study.json) would get report.md, summary.csv and figures/ written over what it holds; another study's folder
    would lend its finished runs to this study (unless ``merge`` asks for that); and a damaged study.json
    cannot tell which study the folder holds."""
    if not out.is_dir():
        return         # made by the run, or refused by it as a file
    recorded = load_study(out)
    if not recorded:
        refuse_other_files(out)
    elif recorded["name"] != name and not merge:
        # as_written: the name comes from a file on disk, which may hold anything (a megabyte of name)
        raise ConfigError("--out", f"{out} holds the study {as_written(recorded['name'])} ({out / STUDY_FILE}), not "
                                   f"{name!r}: give another --out, or add --merge to add this study's runs to that "
                                   "folder")


def refuse_other_files(out: Path) -> None:
    """Refuse a folder without study.json that holds anything but what a study makes before writing one, or runs
    (``<cell>/seed-<n>/result.json``: a study folder whose study.json was removed)."""
    try:
        names = sorted(path.name for path in out.iterdir())
    except OSError as err:
        raise ConfigError("--out", f"cannot read the folder {out}: {err.strerror or err}") from None
    others = [entry for entry in names if entry not in BEFORE_STUDY_JSON]
    if not others or any(out.glob("*/seed-*/result.json")):
        return
    listed = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
    raise ConfigError("--out", f"{out} is not empty ({listed}) and holds no study (no {STUDY_FILE}): a study writes "
                               "report.md, summary.csv and figures/ into its folder, over what is there; give a new "
                               "or empty folder")


def load_study(out_dir: Path) -> Dict[str, Any]:
    """``study.json`` of ``out_dir``, or {} when there is none; a ConfigError naming it when it is not one a study
    wrote. Taken as missing, a damaged file let another study in without --merge, and was replaced, with the
    commands it listed."""
    path = out_dir / STUDY_FILE
    if not path.exists() and not path.is_symlink():
        return {}
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise damaged(path, "not UTF-8 text") from None
    except OSError as err:
        raise ConfigError(str(path), f"cannot be read ({err.strerror or err}): fix or remove it") from None
    try:
        data = parse_json(text) if text.strip() else None
    except ValueError as err:
        raise damaged(path, f"not JSON: {err}") from None
    problem = "empty" if data is None else shape_problem(data)
    if problem:
        raise damaged(path, problem)
    return data


def damaged(path: Path, why: str) -> ConfigError:
    return ConfigError(str(path), f"damaged ({why}): fix or remove it")


def shape_problem(data: Any) -> Optional[str]:
    """What keeps ``data`` from being a study.json (the fields a study reads back), or None."""
    if not isinstance(data, dict):
        return f"not a JSON object: {json.dumps(data)[:40]}"
    if not isinstance(data.get("name"), str):
        return "no study name" if "name" not in data else f"the name is not text: {json.dumps(data['name'])[:40]}"
    for key in ("commands", "planned"):
        if not is_text_list(data.get(key, [])):
            return f"{key} is not a list of text"
    if not isinstance(data.get(UNWRITABLE_KEY, {}), dict):
        return f"{UNWRITABLE_KEY} is not a mapping"
    return None


def is_text_list(value: Any) -> bool:
    return isinstance(value, list) and all(isinstance(item, str) for item in value)


def read_study(out_dir: Path) -> Dict[str, Any]:
    """``study.json`` as far as it can be read, {} otherwise: for the report, which only quotes it."""
    try:
        data = parse_json((out_dir / STUDY_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):      # ValueError: not JSON, or nested past Python's limit
        return {}
    return data if isinstance(data, dict) else {}


def write_study_json(out_dir: Path, data: Dict[str, Any]) -> None:
    path = out_dir / STUDY_FILE
    tmp = out_dir / STUDY_TMP
    tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)
