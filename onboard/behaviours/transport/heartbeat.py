"""When a robot writes its position heartbeat (``pos/<id>`` in the tuple space, see tasks.py) again."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, Optional

# A heartbeat is a new tuple-space version that every robot merges and the swarm relays, so a robot that
# holds still does not repeat it every step: it writes again when it moved this far from the position it
# last wrote (a moving robot at cruise speed still writes every step), when its contact normal appeared,
# vanished or turned this much, and at least this often, well inside the liveness timeout.
HEARTBEAT_MOVE_M = 0.01
HEARTBEAT_TURN_RAD = 0.1
HEARTBEAT_PERIOD_S = 1.0


@dataclass(frozen=True)
class HeartbeatRule:
    """When a robot in one state writes its heartbeat again (a change of state always writes at once)."""

    move_m: Optional[float] = HEARTBEAT_MOVE_M      # it moved this far; None: moving alone never writes
    period_s: float = HEARTBEAT_PERIOD_S            # its last heartbeat is this old
    contact: bool = True                            # its contact normal appeared, vanished or turned


# Every heartbeat is a version that every robot in range merges, which is most of a large swarm's cost
# (docs/performance.md, rounds 3 and 4), so two states write less:
# - A traveller's position only tells the swarm that it is alive: nobody steers by it (a robot steers by its
#   predecessor and the branch tips, which are members, and by range and bearing), so moving does not make
#   it write; the period does.
# - A caged member holds its place, yet its position wanders by a centimetre now and then (spacing
#   corrections, pose noise); others use it for the ring's shape (neighbours in range are steered by range
#   and bearing), where 2 cm is plenty. Nobody asks whether a caged member is alive, nor reads its contact
#   normal, before closure: liveness is consulted for task owners that have not joined the cage (to re-open
#   a dead one's task), for the members that push and estimate (after closure, which changes every member's
#   state and so writes at once), and for whether a spare is cut off (REGROUP_AFTER_S, 30 s); the normals
#   from the push on. So a still caged member writes every 10 s, and its normal flickering with the IR noise
#   does not make it write. (Late in a 100-robot caging some 85 still members wrote once a second, plus the
#   flicker: most of what every robot merged.) A member that dies during caging is still found dead after
#   closure: its last heartbeat is then older than the liveness timeout.
HEARTBEAT_RULES: Dict[str, HeartbeatRule] = {
    "travel": HeartbeatRule(move_m=None),
    "caged": HeartbeatRule(move_m=0.02, period_s=10.0, contact=False),
}
DEFAULT_HEARTBEAT_RULE = HeartbeatRule()


def says_nothing_new(held: list, value: list, rule: HeartbeatRule = DEFAULT_HEARTBEAT_RULE) -> bool:
    """True if the heartbeat ``value`` says nothing new against the one ``held``: moved less than
    ``rule.move_m`` (None: any distance), and the same contact (both none, or normals within
    HEARTBEAT_TURN_RAD; not compared if not ``rule.contact``), and the same surface point (both none, or
    within HEARTBEAT_MOVE_M)."""
    move_m, contact = rule.move_m, rule.contact
    try:
        if move_m is not None and math.hypot(value[0] - held[0], value[1] - held[1]) >= move_m:
            return False
        if (held[3] is None) != (value[3] is None):
            return False
        if held[3] is not None and math.hypot(value[3][0] - held[3][0], value[3][1] - held[3][1]) >= HEARTBEAT_MOVE_M:
            return False
        if not contact:
            return True
        if held[2] is None or value[2] is None:
            return held[2] is None and value[2] is None
        return abs(math.remainder(value[2] - held[2], math.tau)) < HEARTBEAT_TURN_RAD
    except (TypeError, IndexError):                # a malformed value in the space: write a good one
        return False
