"""The telemetry message an agent sends the hub at every step, built in one place: the agent sends it, and the
simulator checks a behaviour's telemetry against its widest form, so that telemetry which passes `sim run`
also fits the wire (``onboard.protocol.MAX_MESSAGE_BYTES``) when an agent sends it in `sil` or the lab."""
from typing import Any, Dict, Optional


def telemetry_message(step: int, mode: str, behaviour: Optional[Dict[str, Any]], loop: Dict[str, Any],
                      battery_v: Optional[float], clock_s: float, frames_lost: int, frames_bad: int, unsent: int,
                      inbox_dropped: int, run_id: Optional[str], driver: str) -> Dict[str, Any]:
    """The fields of one telemetry message; the agent's link adds its robot id and its token."""
    return {
        "type": "telemetry", "step": step, "mode": mode, "behaviour": behaviour, "loop": loop,
        "battery_v": battery_v, "clock_s": clock_s, "frames_lost": frames_lost, "frames_bad": frames_bad,
        "unsent": unsent, "inbox_dropped": inbox_dropped, "run_id": run_id, "driver": driver,
    }


def widest_telemetry_message(behaviour: Optional[Dict[str, Any]]) -> Dict[str, Any]:
    """``behaviour`` in a message whose other fields are as wide as an agent's get in a long run (counters of
    ten digits, a battery voltage and times at full precision), with the id and token the link adds."""
    count = 10 ** 9
    loop = {"hz": 10000.25, "steps": count, "misses": count, "mean_ms": 100000.125, "max_ms": 100000.125}
    message = telemetry_message(count, "watchdog", behaviour, loop, 12.345678901234567, 10000000.123456, count,
                                count, count, count, "f" * 12, "kh4-wide-driver-name")
    message.update(id=999999, agent="f" * 16)
    return message
