"""The hub's side of operator control: ``status``, ``start``, ``stop``, ``estop`` and ``clear`` requests.

Modes: ``idle`` (no run) -> ``run`` (behaviours step) ; ``estop`` is latched until ``clear``, which leaves the
run ``hold`` (wheels stopped, behaviours paused) until the next ``start`` resumes it.
"""
from __future__ import annotations

import time
import uuid
from typing import TYPE_CHECKING, Any, Dict, List, Optional, Tuple

import zmq

from onboard.jsontext import parse_json
from onboard.protocol import MAX_REPLY_BYTES, ProtocolError, decode, encode

from .links import frame_sender
from .new_run import prepare_new_run
from .run_events import outcome_text, run_event

if TYPE_CHECKING:
    from .server import Hub


class ControlService:
    def __init__(self, hub: Hub):
        self.hub = hub

    def handle(self, parts: List[zmq.Frame]) -> None:
        hub = self.hub
        if len(parts) != 2:
            sender = frame_sender(parts[-1], "operator")
            hub.drops.drop("malformed control message", sender, f"{len(parts) - 1} frames from {sender}, expected 1")
            return
        routing, body = parts
        sender = frame_sender(body, "operator")
        try:
            request = decode(body.bytes, sender, accept=("request",))
        except ProtocolError as err:
            hub.drops.drop("bad control message", sender, str(err))
            # A client of its own (a lab script asking for "pause") learns why at once instead of timing out.
            reply: Dict[str, Any] = {"type": "reply", "ok": False, "error": refusal(err)}
            nonce = request_nonce(body.bytes)
        else:
            ok, extra = self.execute(request["cmd"], sender)
            reply = {"type": "reply", "ok": ok, **extra}
            nonce = request.get("nonce")
        if nonce is not None:
            reply["nonce"] = nonce
        try:
            hub.control_socket.send_multipart([routing.bytes, encode_reply(reply)], zmq.NOBLOCK)
        except zmq.ZMQError:
            pass    # the operator left; nothing to do

    def execute(self, cmd: str, sender: str = "operator", note: Optional[str] = None) -> Tuple[bool, Dict[str, Any]]:
        """``note``: why the sender stops the run, for its ``ended`` record (`khepri sil` after a crash)."""
        ok, extra = self._execute(cmd, sender, note)
        if cmd != "status" and self.hub.recorder is not None:
            # With the hub's mode and run after it: a start that resumed a run keeps its run_id, a new run a new one.
            self.hub.recorder.write("/control", {"cmd": cmd, "sender": sender, "ok": ok, **extra,
                                                 "mode": self.hub.mode, "run_id": self.hub.run_id})
        return ok, extra

    def _execute(self, cmd: str, sender: str, note: Optional[str] = None) -> Tuple[bool, Dict[str, Any]]:
        hub = self.hub
        if cmd == "status":
            return True, {"status": self.status(time.monotonic())}
        if cmd == "estop":
            self.estop(sender)
            return True, {"note": self._reach("told to stop") + "; acknowledgements: `khepri ctl status`"}
        if cmd == "clear":
            return self.clear(sender)
        if cmd == "start":
            return self.start(sender)
        if cmd == "stop":
            if hub.mode == "estop":
                return False, {"error": "the e-stop is latched: `khepri ctl clear` first"}
            return self.stop(sender, note)
        return False, {"error": f"unknown command {cmd!r}"}

    def clear(self, sender: str) -> Tuple[bool, Dict[str, Any]]:
        hub = self.hub
        if hub.mode != "estop":
            return True, nothing_done("nothing to clear: no e-stop was latched")
        hub.mode = "hold" if hub.run_id is not None else "idle"
        hub.estop_at = None         # cleared: its acknowledgement times are history (status showed them)
        for robot in hub.robots.values():
            robot.estop_ack_s = None
        hub.log(f"hub: e-stop cleared by {sender}; robots stay stopped until `khepri ctl start`")
        hub.send_command_to_all("clear")
        return True, {"note": "robots stay stopped until `khepri ctl start`"}

    def estop(self, sender: str) -> None:
        hub = self.hub
        hub.mode = "estop"
        hub.estop_at = time.monotonic()
        for robot in hub.robots.values():
            robot.estop_ack_s = None
        hub.send_command_to_all("estop", "operator e-stop")   # before anything else: this is the urgent part
        hub._hold_sim_wheels(time.monotonic())
        hub.log(f"hub: E-STOP by {sender}: {self._reach('told to stop')} (latched until `khepri ctl clear`)")

    def start(self, sender: str) -> Tuple[bool, Dict[str, Any]]:
        hub = self.hub
        if hub.mode == "estop":
            return False, {"error": "the e-stop is latched: `khepri ctl clear` first"}
        if hub.mode == "run":
            return True, nothing_done(f"nothing to start: run {hub.run_id} is already going")
        if hub.mode == "idle":
            hub.run_id = uuid.uuid4().hex[:12]
            hub.runs_started.add(hub.run_id)
            hub.estop_at = None             # a new run: the last e-stop's acknowledgement times are history
            for robot in hub.robots.values():
                robot.estop_ack_s = None
            reset = prepare_new_run(hub)       # before the agents hear of the run: its first frames are its own
            hub.send_command_to_all("start")
            if hub.progress is not None:
                hub.progress.start(hub.source.time_s, hub.source.world)
            run_event(hub, hub.run_id, "started", "start", sender)
            back = "the replay is back at the log's start" if hub.config.source.type == "replay" \
                else "the world is back at the scenario's start"
            hub.log(f"hub: run {hub.run_id} started by {sender}: {hub.run.behaviour}" + (f"; {back}" if reset else ""))
        else:
            hub.log(f"hub: run {hub.run_id} resumed by {sender}")
        resumed = hub.mode == "hold"        # after `clear`: the operator is told it is the same run going on
        hub.mode = "run"
        # An agent that cannot start it (a behaviour it cannot import, bad params) says so in its telemetry,
        # after this reply: the operator is pointed at the status, where its error shows.
        note = (f"run {hub.run_id} resumed; " if resumed else "") + self._reach("sent it") \
            + "; an agent that cannot run it says so in `khepri ctl status`"
        return True, {"note": note + self._held()}

    def _held(self) -> str:
        """The robots the run starts without, and why: four robots outside the geofence heard `start: ok` and
        stood still, the cage never closing, with nothing said but in the status table."""
        held = [(robot.id, why) for robot in self.hub.robots.values()
                for mode, why in [self.hub.mode_for(robot)] if mode == "hold"]
        if not held:
            return ""
        listed = ", ".join(f"robot {rid} ({why})" for rid, why in held[:6]) + (" ..." if len(held) > 6 else "")
        return f"; HELD, not running: {listed}"

    def _reach(self, what: str) -> str:
        """How many robots a command reached, naming the others when some are there: '4 of 6 robots connected
        and told to stop (not connected: robot 2, robot 5)'. On a demo night the count alone left the
        operator to find the missing two in the status table."""
        now = time.monotonic()
        missing = [robot.id for robot in self.hub.robots.values()
                   if not robot.connected(now, self.hub.config.watchdog_s)]
        reached = f"{len(self.hub.robots) - len(missing)} of {len(self.hub.robots)} robots connected and {what}"
        if missing and len(missing) == len(self.hub.robots):     # "ok (0 of 6 ...)" was easy to misread
            return f"NO ROBOT CONNECTED (0 of {len(self.hub.robots)}): each is {what} as it connects"
        if not missing:
            return reached
        listed = ", ".join(f"robot {rid}" for rid in missing[:6]) + (" ..." if len(missing) > 6 else "")
        return f"{reached} (not connected: {listed})"

    def stop(self, sender: str, note: Optional[str] = None) -> Tuple[bool, Dict[str, Any]]:
        """Ends the run. Without one, the robots are told to stop all the same (an agent may hold a run of an
        earlier hub), but the operator is told there was nothing to stop rather than a bare "ok"."""
        hub = self.hub
        run_id = hub.run_id
        hub.mode = "idle"
        hub.run_id = None
        for robot in hub.ids:      # the ended run's messages still queued (a robot out of reach) are no one's now:
            hub.relay.clear(robot)  # a robot that connected while idle got them, with no way to tell their run
        hub.send_command_to_all("stop")
        hub._hold_sim_wheels(time.monotonic())
        if run_id is None:
            return True, nothing_done("nothing to stop: no run is going")
        outcome = outcome_text(run_event(hub, run_id, "ended", "stop", sender, note))
        hub.log(f"hub: run {run_id} stopped by {sender}" + (f": {outcome}" if outcome else ""))
        return True, {"note": f"run {run_id} ended; " + self._reach("told to stop")}

    def status(self, now: float) -> Dict[str, Any]:
        hub = self.hub
        rows = [robot.status_row(now, hub.config.watchdog_s, *self._status_mode(robot))
                for robot in hub.robots.values()]
        return {
            "mode": hub.mode,
            "run_id": hub.run_id,
            "behaviour": hub.run.behaviour,
            "source": hub.source.description,
            "mocap_hz": round(hub.mocap_rate.current(now), 1),
            "clock_s": hub.clock_s,
            "uptime_s": round(now - hub.started_at, 3),
            "cpu_s": round(time.process_time(), 4),
            "secure": hub.keyring is not None,
            "recording": recording_status(hub.recorder),
            "drops": dict(hub.drops.counts),
            "relay": hub.relay.stats.as_dict(),
            "robots": rows,
            "object": hub.progress.status() if hub.progress is not None else None,   # sim source only
            "replay": hub.source.progress(),          # replay source only
        }

    def _status_mode(self, robot: Any) -> Tuple[str, str]:
        """``mode_for``, with the geofence said before a run too: a robot outside it showed a plain `idle` until
        `start`, when it was held."""
        mode, reason = self.hub.mode_for(robot)
        if not reason and mode in ("idle", "hold") and self.hub.outside_fence[self.hub.row[robot.id]]:
            reason = "outside the geofence: held when a run starts" if mode == "idle" else "outside the geofence"
        return mode, reason


def nothing_done(why: str) -> Dict[str, Any]:
    """A reply's extra fields for a command that had nothing to act on: ``khepri ctl`` prints ``why`` instead of
    "ok", and exits 0 all the same (the hub is in the state the operator asked for)."""
    return {"note": why, "nothing_done": True}


def recording_status(recorder: Any) -> Optional[Dict[str, Any]]:
    """None when the hub does not record; else the log's path, once a write failed why it stopped, and how many
    messages were left out while the disk fell behind."""
    if recorder is None:
        return None
    return {"path": str(recorder.path), "error": getattr(recorder, "failure", None),
            "left_out": getattr(recorder, "left_out", 0)}


def refusal(err: ProtocolError) -> str:
    return f"refused: {err.field}: {err.problem}" if err.field else f"refused: {err.problem}"


def request_nonce(data: bytes) -> Optional[int]:
    """The nonce of a request that failed validation, when it has a usable one, so its refusal is matched."""
    try:
        nonce = parse_json(data).get("nonce")
    except (ValueError, AttributeError):    # not JSON (nested past the recursion limit too), not an object
        return None
    return nonce if type(nonce) is int and 0 <= nonce < 1 << 53 else None


def encode_reply(reply: Dict[str, Any]) -> bytes:
    """The reply, or, when it is over the protocol's message limit (the status of a few hundred connected
    robots), a refusal that says so: the hub must not die of an operator's question."""
    try:
        return encode(reply, MAX_REPLY_BYTES)
    except ProtocolError as err:
        refusal = {"type": "reply", "ok": False, "error": f"the reply is too large to send ({err.problem})"}
        if "nonce" in reply:
            refusal["nonce"] = reply["nonce"]
        return encode(refusal)
