"""A run's start, its arrival at the last waypoint and its end, said on the hub's console and recorded on
``/hub/run`` (docs/recording.md), with the object's progress and the outcome when the hub knows them (the
``sim`` source: ``hub/progress.py``).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Dict, Optional

from .control import object_text
from .log_format import HUB_RUN

if TYPE_CHECKING:
    from .server import Hub


def follow_progress(hub: Hub) -> None:
    """Each new control step of a run: the evaluator sees it, and the arrival at the last waypoint is said once."""
    progress = hub.progress
    if progress is None or hub.mode != "run" or hub.run_id is None:
        return
    if not progress.follow(hub):
        return
    count = len(progress.scenario.path)
    if count and hub.arrival_said != hub.run_id and progress.reached() == count:
        hub.arrival_said = hub.run_id
        event = run_event(hub, hub.run_id, "all waypoints reached", "waypoints", "the swarm")
        # The outcome first: "all 3 waypoints reached: not completed" read as a contradiction (a waypoint passed
        # 0.101 m off, or the object turned past the tolerance, on the way).
        outcome = outcome_text(event)
        if event.get("outcome") == "not completed":
            why = "; ".join(part for part in ((event.get("failures") or ["?"])[0],
                                               object_text(event.get("object"))) if part)
            hub.log(f"hub: run {hub.run_id}: NOT completed, although the object passed all {count} waypoints: "
                    f"{why}{stop_hint(hub)}")
        else:
            hub.log(f"hub: run {hub.run_id}: all {count} waypoints reached: {outcome}{stop_hint(hub)}")


def stop_hint(hub: Hub) -> str:
    """How the operator ends a run that is done; not in `khepri sil`, which ends it itself (its hub runs the
    lockstep)."""
    return "" if hub.run.lockstep else "; `khepri ctl stop` ends the run"


def run_event(hub: Hub, run_id: str, event: str, cause: str, by: str, note: Optional[str] = None) -> Dict[str, Any]:
    """The ``/hub/run`` record of a run's ``started``, ``all waypoints reached`` or ``ended``, with the object's
    progress and (but at the start) the outcome when the hub knows them, and ``note``, why whoever ended it did
    (`khepri sil`: an agent or the evaluator crashed, Ctrl-C); recorded when the hub records."""
    record: Dict[str, Any] = {"run_id": run_id, "event": event, "cause": cause, "by": by,
                              "behaviour": hub.run.behaviour}
    if note:
        record["note"] = note
    if hub.progress is not None:
        record["object"] = hub.progress.status()
        if event != "started":
            record.update(hub.progress.verdict())
    if hub.recorder is not None:
        hub.recorder.write(HUB_RUN, record)
    return record


def outcome_text(record: Dict[str, Any]) -> str:
    """'completed; object at ...' or 'not completed (reached 1 of 3 waypoints); object at ...' from a ``/hub/run``
    record; '' when the hub knows neither (motion capture)."""
    outcome, failures = record.get("outcome"), record.get("failures") or []
    said = f"{outcome} ({failures[0]})" if outcome == "not completed" and failures else outcome
    return "; ".join(part for part in (said, object_text(record.get("object"))) if part)


def end_by_signal(hub: Hub, name: str) -> str:
    """A hub stopped by SIGINT, SIGTERM or SIGHUP ends its run with it: said, naming the run and the signal, and
    recorded as the run's ``ended`` record among the log's closing ones. The words its last line, ``hub: stopped``,
    ends with."""
    run_id = hub.run_id
    if run_id is None:
        return f" by {name} (no run was going)"
    outcome = outcome_text(run_event(hub, run_id, "ended", "signal", name))
    hub.log(f"hub: {name}: run {run_id} ended by the signal" + (f": {outcome}" if outcome else ""))
    hub.mode, hub.run_id = "idle", None
    return f" by {name}; run {run_id} ended"
