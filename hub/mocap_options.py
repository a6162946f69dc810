"""Which ``source.options`` each backend of the ``motioncapture`` library reads.

The library passes the options to its C++ ``connect()``, which looks up the keys it knows and ignores the rest
without a word: ``host: 10.0.0.5`` for a Vicon (its key is ``hostname``) connected to localhost and timed out,
and a mock's ``frequncy: 30`` ran at 100 Hz. The keys below are those of motioncapture 1.x's ``connect()``
(spelling included: its Vicon reads ``enable_pointclout``). A newer library may read more, so for a real system
an unknown key is a warning; the mock, which the hub benchmark and tests use, is checked strictly."""
from __future__ import annotations

import difflib
from typing import Dict, Iterable, List, Optional

from onboard.config import ConfigError, join

READ_OPTIONS: Dict[str, tuple] = {
    "mock": ("rigid_bodies", "pointcloud", "frequency"),
    "vicon": ("hostname", "enable_objects", "enable_pointclout"),
    "optitrack": ("hostname", "interface_ip", "port_command"),
    "optitrack_closed_source": ("hostname", "port_command"),
    "qualisys": ("hostname", "port", "enable_objects", "enable_pointcloud"),
    "nokov": ("hostname", "enableFrequency", "updateFrequency"),
    "vrpn": ("hostname",),
    "motionanalysis": ("hostname",),
    "fzmotion": ("local_IP", "local_port", "hostname", "remote_port"),
}

# A quaternion this far from unit length (its squared norm) is no orientation: all zeros, as some systems give
# for a body they lost. Its yaw would read as 0, facing +x: the hub takes it as no pose (hub/sources.py), and a
# mock body written so is refused (hub/config.py).
DEGENERATE_QUATERNION = 0.25


def unread_option_notes(system: str, options: Iterable[str]) -> List[str]:
    """One sentence per option ``system`` does not read (none for a system this table does not know)."""
    known = READ_OPTIONS.get(system)
    if known is None:
        return []
    return [f"source.options.{name}: motioncapture 1.x's {system} backend does not read it; passed on all the "
            f"same (it reads {', '.join(known)}){did_you_mean(name, known)}"
            for name in options if name not in known]


def check_mock_options(where: str, options: Iterable[str]) -> None:
    """The mock ignores a key it does not know: a typo would run with its default without a word."""
    known = READ_OPTIONS["mock"]
    for name in options:
        if name not in known:
            raise ConfigError(join(where, name), f"the mock backend does not read it (it reads {', '.join(known)})"
                              + did_you_mean(name, known))


def did_you_mean(name: str, known: Iterable[str]) -> str:
    """'; did you mean rate?' for the nearest of ``known`` to a mistyped key, '' when none is near."""
    known = list(known)
    close: Optional[List[str]] = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    if not close and name.lower() in ("host", "ip", "address", "server"):
        close = ["hostname"] if "hostname" in known else None
    return f"; did you mean {close[0]}?" if close else ""


def known_systems_hint(reason: str) -> str:
    """After the library's "Unknown motion capture type!": the systems motioncapture 1.x has (a build may
    leave some out)."""
    if "unknown motion capture type" not in reason.lower():
        return ""
    return f" (motioncapture 1.x knows {', '.join(READ_OPTIONS)}; this build may lack some)"
