"""What a SIL run writes besides the evaluator's keys: the trajectory (same NPZ keys as ``khepri sim run``,
see docs/outputs.md) and the hub/agent figures under ``result["sil"]``."""
from __future__ import annotations

from typing import Any, Dict, List, Optional

import numpy as np

from sim_backend.trajectory import trajectory_arrays


class SilRecording:
    """Samples per control step; ``trajectory_arrays()`` is what ``sim_backend.outputs.write_run`` reads."""

    def __init__(self, scenario, world):
        self.scenario, self.world = scenario, world
        self.t: List[float] = []
        self.robot_pose: List[np.ndarray] = []
        self.robot_alive: List[np.ndarray] = []
        self.object_pose: List[np.ndarray] = []
        self.centroid_estimate: List[np.ndarray] = []

    def add(self, t: float, world, centroid_estimate: np.ndarray) -> None:
        self.t.append(t)
        self.robot_pose.append(world.robot_poses())
        self.robot_alive.append(world.alive())
        obj = world.object_pose()
        if obj is not None:
            self.object_pose.append(obj)
        self.centroid_estimate.append(np.asarray(centroid_estimate, dtype=float))

    def trajectory_arrays(self) -> Dict[str, np.ndarray]:
        return trajectory_arrays(self, self.scenario, self.world)


def agents_total(hub, key: str) -> int:
    """The sum over the agents of a count in their last telemetry (``frames_lost``, ``inbox_dropped``, ...)."""
    return sum(int((r.telemetry or {}).get(key) or 0) for r in hub.robots.values())


def sil_figures(hub, lockstep, round_trips: List[float], missing_answers: int, is_lockstep: bool) -> Dict[str, Any]:
    """Hub and agent figures: frame-to-answer latency, agents' loop timing and misses, every kind of drop."""
    loops = [((r.telemetry or {}).get("loop") or {}) for r in hub.robots.values()]
    return {
        "agents": len(hub.robots),
        "lockstep": is_lockstep,
        "steps": lockstep.steps if is_lockstep else None,
        "latency_ms": {  # hub sends a frame -> the agent's answer (its step ran in between) arrives
            "p50": _percentile_ms(round_trips, 50), "p99": _percentile_ms(round_trips, 99),
            "max": _percentile_ms(round_trips, 100)},
        "step_timeouts": lockstep.timeouts if is_lockstep else None,
        "missing_answers": missing_answers,
        "loop_misses": sum(int(loop.get("misses") or 0) for loop in loops),
        "loop_step_ms": {"mean": _mean([loop.get("mean_ms") for loop in loops]),
                         "max": max([loop.get("max_ms") or 0.0 for loop in loops], default=None)},
        "dropped": {
            # what the hub refused from the agents; its own full downlink queues are counted just below
            "hub_rejected": {k: v for k, v in hub.drops.counts.items() if k != "downlink queue full"},
            "downlink_queue_full": sum(r.frames_dropped for r in hub.robots.values()),
            "frames_lost_at_agents": agents_total(hub, "frames_lost"),
            "bad_frames_at_agents": agents_total(hub, "frames_bad"),
            "unsent_at_agents": agents_total(hub, "unsent"),   # the agents' sockets were full: never left
            "inbox_overflow_at_agents": agents_total(hub, "inbox_dropped"),   # > Radio.INBOX_LIMIT in a step
            "relay": hub.relay.stats.as_dict(),
        },
    }


def _percentile_ms(values: List[float], q: float) -> Optional[float]:
    return round(float(np.percentile(values, q)) * 1000.0, 3) if values else None


def _mean(values: List[Any]) -> Optional[float]:
    numbers = [v for v in values if isinstance(v, (int, float))]
    return round(sum(numbers) / len(numbers), 3) if numbers else None


_DROP_WORDS = {
    "downlink_queue_full": "frames the hub could not queue for an agent",
    "frames_lost_at_agents": "frames lost on the way to the agents",
    "bad_frames_at_agents": "bad frames at the agents",
    "unsent_at_agents": "messages the agents could not send",
    "inbox_overflow_at_agents": "radio messages pushed out of full inboxes",
}
_RELAY_WORDS = {
    "dropped_random": "radio messages lost by chance (the scenario's comm.drop)",
    "dropped_overflow": "radio messages pushed out of full relay queues",
    "refused": "broadcasts the relay refused (over relay.max_bytes, or sent outside a run)",
}


def sil_summary_lines(sil: Dict[str, Any]) -> List[str]:
    """What ``khepri sil`` prints under the run's summary: the figures in words, and every drop by its kind."""
    latency = (sil.get("latency_ms") or {}).get("p99")
    if latency is not None:
        timing = f"frame-to-answer latency p99 {latency:g} ms"
    elif sil.get("lockstep"):      # a lockstep run that ended before any frame was answered (a crash at t = 0)
        timing = "frame-to-answer latency not measured (no frame was answered)"
    else:
        timing = "frame-to-answer latency not measured (--realtime: the agents run on their own clocks)"
    mode = "lockstep" if sil.get("lockstep") else "real time"
    lines = [f"  {sil.get('agents')} agents, {mode}, {timing}, loop misses {sil.get('loop_misses', 0)}"]
    dropped = sil.get("dropped") or {}
    relay, rejected = dropped.get("relay") or {}, dropped.get("hub_rejected") or {}
    said = [f"{dropped[key]} {words}" for key, words in _DROP_WORDS.items() if dropped.get(key)]
    said += [f"{relay[key]} {words}" for key, words in _RELAY_WORDS.items() if relay.get(key)]
    said += [f"{count} messages the hub refused: {reason}" for reason, count in rejected.items()]
    # hub.log names what was dropped and why, but for the radio's chance losses, which it only counts
    chance_only = not any(relay.get(key) for key in _RELAY_WORDS if key != "dropped_random") \
        and not any(dropped.get(key) for key in _DROP_WORDS) and not rejected
    more = "" if chance_only else " (hub.log says more)"
    lines.append(f"  dropped: {'; '.join(said)}{more}" if said else "  dropped: nothing")
    return lines
