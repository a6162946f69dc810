"""The agent: runs one behaviour at the control rate through a HAL backed by hub frames and a driver.

Safety rules, in order of precedence:

- the hub's mode: ``estop`` and ``hold`` stop the wheels at once and pause the behaviour; ``idle`` has none;
- the watchdog: no frame from the hub for ``watchdog_s`` (0.25 s) -> wheels stopped, behaviour held, until
  frames return;
- leaving for any reason (SIGINT, SIGTERM, SIGHUP, an exception in the behaviour) stops the wheels first;
- wheel commands pass only in ``run`` mode with live frames, from whatever thread they come, and a step that
  runs longer than the watchdog has the wheels stopped by a thread of its own (``safety.py``).

Pacing: in real time the loop ticks on its own clock at ``control_hz``; in lockstep (SIL) it ticks once per
hub frame. Everything else is the same code, except that in lockstep neither watchdog stops the wheels: they
are the hub's simulated ones, which move only once this agent has answered its frame.
"""
from __future__ import annotations

import math
import random
import signal
import time
from typing import Any, Callable, Dict, List, Optional

from onboard.behaviour import (
    USER_CODE_ERRORS,
    Behaviour,
    BehaviourError,
    build_params,
    get_behaviour,
    ignored_return_text,
    plain_json,
    telemetry_of,
)
from onboard.config import ConfigError, check_boolean
from onboard.console import stop_signals
from onboard.drivers import Driver, DriverError
from onboard.protocol import IDLE_TELEMETRY_HZ, ProtocolError
from onboard.protocol_schema import TEXT_MAX_CHARS

from .devices import AgentClock, HubState, apply_frame, make_robot
from .link import HubLink, family_hint
from .loop_stats import LoopStats
from .run_start import run_control_hz, run_id_text, run_params, run_spec, run_uses_hub_clock
from .safety import GuardedDriver, StepWatchdog
from .telemetry_message import telemetry_message

SLOW_STEP_REPEAT_S = 10.0  # a behaviour whose step outlasts the watchdog is said at most this often
HELLO_PERIOD_S = 0.5      # while the hub is silent (or has not given us the run), say hello this often
RESET_AFTER_S = 2.0       # this long without a frame: reopen the socket (a connection can be stuck for good)
# In lockstep (SIL) the hub is silent while it waits for the slowest agent, up to its step timeout (2 s) each
# step, and longer on a loaded machine: a reopened socket there lost the frame in flight and the robot's step.
LOCKSTEP_RESET_AFTER_S = 10.0
WAITING_LOG_S = 10.0      # while the hub stays silent, say so this often


class Agent:
    def __init__(self, robot_id: int, link: HubLink, driver_factory: Callable[[Agent], Driver],
                 watchdog_s: float = 0.25, log: Callable[[str], None] = print):
        self.robot_id, self.link, self.log = robot_id, link, log
        self.watchdog_s = watchdog_s
        self.state = HubState()
        self.clock = AgentClock(self.state)
        self.driver = GuardedDriver(driver_factory(self))
        self.behaviour: Optional[Behaviour] = None
        self.run: Optional[Dict[str, Any]] = None
        self.error: Optional[str] = None
        self.refused_run_id: Any = None        # the run this agent could not start: said once, not per frame
        self.period = 1.0 / IDLE_TELEMETRY_HZ     # the loop's (and telemetry's) rate until a run sets it
        self.stats = LoopStats()
        self.next_tick = time.monotonic()
        self.answered_seq = 0
        self.watchdog_tripped = False
        self.last_hello = -math.inf
        self.last_reset = time.monotonic()
        self.last_waiting_log = -math.inf
        self.stop_requested = False
        self.stop_signal: Optional[int] = None     # the signal that asked the agent to leave, said on the way out
        self.slow_step_said_at = -math.inf
        self.return_said = False          # a step() that returned something was said (once)
        self.watchdog_said = False        # the watchdog's trip was logged (so its end is logged too)
        self.step_watchdog = StepWatchdog(self.driver, watchdog_s, lambda: self.stop_requested, log, robot_id)

    # --- main loop ----------------------------------------------------------------------------------------
    def serve(self, should_stop: Callable[[], bool] = lambda: False) -> None:
        """Run until ``should_stop()`` or a signal; the wheels are stopped on every way out."""
        previous = self._install_signal_handlers()
        self.step_watchdog.start()
        try:
            self.hello(time.monotonic())
            while not (self.stop_requested or should_stop()):
                self.loop_once()
        finally:
            self.step_watchdog.stop()
            self._stop_behaviour()         # leaving mid-run (SIGTERM before the hub's stop): its stop() too
            self._stop_wheels_on_the_way_out()
            farewell: Dict[str, Any] = {"type": "telemetry", "step": self.state.seq, "mode": "exiting"}
            if self.error:                 # the last word the hub hears must still say why
                farewell["error"] = error_for_the_hub(self.error)
            self.link.send(farewell)
            self._restore_signal_handlers(previous)
            self._say_why_leaving()

    def _say_why_leaving(self) -> None:
        """Said last, once the wheels are stopped and the hub told: after SIGHUP the console may be gone."""
        if self.stop_signal is not None:
            self.log(f"agent {self.robot_id}: {signal.Signals(self.stop_signal).name}: wheels stopped, leaving")

    def _stop_wheels_on_the_way_out(self) -> None:
        """Stop the wheels as the agent leaves; a driver that cannot (the bus is gone) is said in one line and
        in the farewell telemetry, and the exception that got us here goes on (the wheel guard tries next)."""
        try:
            self.driver.close_gate()
        except DriverError as err:
            self.error = self.error or f"driver failed: cannot stop the wheels: {err}"
            self.log(f"agent {self.robot_id}: cannot stop the wheels: {err}")

    def loop_once(self) -> None:
        now = time.monotonic()
        for message in self.link.receive(self._wait_time(now)):
            self.handle(message, time.monotonic())
        now = time.monotonic()
        self.check_watchdog(now)
        silent_s = now - max(self.state.received_at, self.last_reset)
        if silent_s > (LOCKSTEP_RESET_AFTER_S if self._lockstep() else RESET_AFTER_S):
            self.last_reset = now
            self._say_still_waiting(now)      # before the reset: what became of this connection tells why
            self.link.reset()
        if silent_s > self.watchdog_s or (self.state.mode != "idle" and self.run is None):
            if now - self.last_hello >= HELLO_PERIOD_S:
                self.hello(now)
        if self._tick_due(now):
            self.tick(now)

    def _say_still_waiting(self, now: float) -> None:
        """Every WAITING_LOG_S of silence, one line, so that a wrong --hub, a hub not running or keys it does
        not list show up on the robot's console instead of a quiet robot."""
        if now - self.last_waiting_log < WAITING_LOG_S:
            return
        self.last_waiting_log = now
        since = "yet" if self.state.received_at == -math.inf else f"for {now - self.state.received_at:.0f} s"
        cause = self.link.likely_cause()
        if cause is not None:
            self.log(f"agent {self.robot_id}: no frame from the hub at {self.link.endpoint} {since}; still trying: "
                     f"{cause}")
            return
        key = (", does the hub list this robot's key, or does it run --insecure (then leave out --keys)"
               if self.link.keys is not None else "")
        self.log(f"agent {self.robot_id}: no frame from the hub at {self.link.endpoint} {since}; still trying "
                 f"(is the hub running, is another agent already connected as robot {self.robot_id}, are --hub and "
                 f"--port the host and robots port it printed when it started, is robot {self.robot_id} in the hub's "
                 f"lab{key}?) {family_hint(self.link.endpoint)}".rstrip())

    def _lockstep(self) -> bool:
        return bool(self.run and self.run.get("lockstep"))

    def _wait_time(self, now: float) -> float:
        watchdog_left = self.state.received_at + self.watchdog_s - now
        if self._lockstep():
            return 0.02                # frames pace the loop; no watchdog to check on time (check_watchdog)
        wait = self.next_tick - now
        if not self.watchdog_tripped:
            wait = min(wait, max(0.0, watchdog_left) + 0.001)
        return max(0.0, min(wait, 0.05))

    def _tick_due(self, now: float) -> bool:
        if self._lockstep():
            return self.state.seq > self.answered_seq
        return now >= self.next_tick

    # --- messages -----------------------------------------------------------------------------------------
    def handle(self, message: Dict[str, Any], now: float) -> None:
        if message["type"] == "frame":
            apply_frame(self.state, message, self.clock, now)
            if self.watchdog_tripped:
                self.watchdog_tripped = False
                if self.watchdog_said:         # not at the first frame: the watchdog trips quietly before it
                    self.log(f"agent {self.robot_id}: hub frames are back")
                self.watchdog_said = False
            self.apply_mode(message["mode"], message.get("reason", ""))
        else:
            self.on_command(message)

    def on_command(self, message: Dict[str, Any]) -> None:
        cmd = message["cmd"]
        if cmd == "estop":
            self.apply_mode("estop", message.get("reason", "e-stop"))
        elif cmd == "clear":
            self.apply_mode("hold", "e-stop cleared")
        elif cmd == "stop":
            if self.run is not None:     # said: the operator's stop, or the hub going away
                why = message.get("reason")
                self.log(f"agent {self.robot_id}: run stopped{': ' + why if why else ''}")
            self.end_run()
            self.apply_mode("idle", "")
        elif cmd == "start":
            self.start_run(message.get("run") or {})
        self.link.send({"type": "ack", "cmd": cmd, "seq": self.state.seq})   # after acting: wheels already stopped

    def apply_mode(self, mode: str, reason: str) -> None:
        if mode == self.state.mode:
            return
        if mode != "run":
            self.driver.close_gate()      # hold, estop and idle never leave a wheel turning
        if mode in ("estop", "hold"):
            self.log(f"agent {self.robot_id}: {mode}{': ' + reason if reason else ''}")
        elif mode == "run" and self.state.mode in ("estop", "hold") and self.run is not None:
            # Said as the hold was: a log that ended at "hold: e-stop cleared" read as a robot that never moved again.
            self.log(f"agent {self.robot_id}: run {self.run.get('run_id')} goes on (was {self.state.mode})")
        self.state.mode = mode
        self.state.reason = reason

    def start_run(self, run: Dict[str, Any]) -> None:
        if self.run is not None and run.get("run_id") == self.run.get("run_id"):
            return                 # a repeated start: we already have this run
        if self.run is None and self.error and run.get("run_id") == self.refused_run_id:
            return                 # the hub repeats a start until acked; the error is said and in telemetry
        self.end_run()
        try:
            cls = get_behaviour(str(run.get("behaviour")), "run.behaviour")
            params = build_params(cls, run_params(run.get("params")), "run.params")
            spec = run_spec(run.get("spec"))
            period = 1.0 / run_control_hz(run.get("control_hz", 10.0))
            run_id_text(run.get("run_id"))
            check_boolean("run.lockstep", run.get("lockstep", False))    # _lockstep() reads it at every tick
            hub_clock = run_uses_hub_clock(run.get("clock", "local"))
        except (ConfigError, TypeError, ValueError) as err:
            self.error = f"cannot start the run: {err}"
            run_id = run.get("run_id")
            self.refused_run_id = run_id if isinstance(run_id, str) else None   # telemetry carries text only
            self.log(f"agent {self.robot_id}: {self.error}")
            return
        self.error = None
        self.run, self.period = run, period
        self.stats = LoopStats()          # status and SIL count this run's steps and misses, not the agent's life's
        self.clock.restart(hub_clock)
        # Messages relayed after the last run's last step (the hub's queue at `stop`) wait in the inbox; the
        # new behaviour would take them as this run's (transport: the old cage "closed", no seed elected).
        self.state.inbox.clear()
        seed = run.get("seed")
        if isinstance(seed, int) and not isinstance(seed, bool):
            # As the simulator seeds `random` for its behaviours: a run with a seed repeats, agent by agent.
            random.seed(seed * 1_000_003 + self.robot_id)
        robot = make_robot(self.robot_id, self.state, self.clock, self.driver, self.link.send, spec)
        try:
            self.behaviour = cls(robot, params)
        except USER_CODE_ERRORS as exc:
            self.behaviour_failed(BehaviourError(self.robot_id, f"{cls.__name__}.__init__", exc))   # raises
        self.answered_seq = self.state.seq
        self.next_tick = time.monotonic()
        self.log(f"agent {self.robot_id}: run {run.get('run_id')}: {run.get('behaviour')}")

    def end_run(self) -> None:
        self._stop_behaviour()
        self.behaviour, self.run = None, None
        self.driver.close_gate()

    def _stop_behaviour(self) -> None:
        """The behaviour's own ``stop()``; one that raises is logged, and must not keep the wheels turning."""
        if self.behaviour is not None:
            try:
                self.behaviour.stop()
            except USER_CODE_ERRORS as exc:
                self.log(f"agent {self.robot_id}: {BehaviourError(self.robot_id, 'stop()', exc)}")

    def behaviour_failed(self, err: BehaviourError) -> None:
        """The behaviour's code raised: the wheels stop, the hub hears why (telemetry ``error``: its status
        and SIL show it), the log gets the traceback, and the agent ends (``serve`` stops the wheels again
        on the way out)."""
        self._stop_wheels_on_the_way_out()
        self.behaviour = None
        # The robot's own hardware failing inside step() (IR, encoders) is not the behaviour's bug.
        what = "driver failed" if isinstance(err.exc, DriverError) else "behaviour crashed"
        self.error = f"{what}: {err} (at t = {self.clock.now():.1f} s)"
        self.log(f"agent {self.robot_id}: {self.error}")
        for line in err.lines:
            self.log(f"agent {self.robot_id}:   {line}")
        err.traceback_logged = True       # khepri's last line does not print the same traceback again
        self.send_telemetry(stepped=False)
        raise err

    def hello(self, now: float) -> None:
        self.last_hello = now
        self.link.send({"type": "hello", "driver": self.driver_name(),
                        "run_id": self.run.get("run_id") if self.run else None})

    def driver_name(self) -> str:
        return self.driver.name or type(self.driver).__name__

    # --- safety -------------------------------------------------------------------------------------------
    def check_watchdog(self, now: float) -> None:
        if self._lockstep():
            # Lockstep wheels are the hub's simulated ones, which move only when the hub advances physics, after
            # this agent answered (or timed out). A stop sent while the hub waited for a slower agent landed in
            # the step being waited on, and the run then depended on the machine's load.
            return
        if not self.watchdog_tripped and now - self.state.received_at > self.watchdog_s:
            self.watchdog_tripped = True
            self.driver.close_gate()
            # After a step slower than the watchdog, the frames waited for us: tick() has said so already.
            if self.state.received_at > -math.inf and self.stats.last_step_s <= self.watchdog_s:
                self.log(f"agent {self.robot_id}: no frame from the hub for {self.watchdog_s:g} s: wheels stopped")
                self.watchdog_said = True

    # --- one control step ---------------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        started = time.monotonic()
        scheduled = started if self._lockstep() else self.next_tick
        stepped = self.behaviour is not None and self.state.mode == "run" and not self.watchdog_tripped
        if stepped:
            self.driver.open_gate()
            self.step_watchdog.begin(stops_wheels=not self._lockstep())
            try:
                returned = self.behaviour.step()
                if returned is not None and not self.return_said:     # (e.g. wheel speeds: sim run says it too)
                    self.return_said = True
                    self.log(f"agent {self.robot_id}: warning: step() returned {ignored_return_text(returned)}")
            except USER_CODE_ERRORS as exc:
                self.behaviour_failed(BehaviourError(self.robot_id, "step()", exc))
            finally:
                self.step_watchdog.end()
            finished = time.monotonic()
            self.stats.record(started, finished, scheduled + self.period)
            self._say_if_slow(finished - started, finished)
        else:
            self.stats.idle(started)
        self.answered_seq = self.state.seq
        self.send_telemetry(stepped)
        finished = time.monotonic()
        self.next_tick = scheduled + self.period
        if self.next_tick <= finished:            # behind by a whole period: skip ahead instead of bursting
            self.next_tick = finished + self.period

    def _say_if_slow(self, step_s: float, now: float) -> None:
        """A step longer than the watchdog leaves the robot without fresh frames for that long (and may trip
        the watchdog, which would otherwise seem to blame the hub): say so, at most every 10 s."""
        if step_s > self.watchdog_s and now - self.slow_step_said_at >= SLOW_STEP_REPEAT_S:
            self.slow_step_said_at = now
            self.log(f"agent {self.robot_id}: the behaviour's step took {step_s:.2f} s, longer than the "
                     f"{self.watchdog_s:g} s watchdog: the robot acts on old frames or stops (make step() faster)")

    def send_telemetry(self, stepped: bool) -> None:
        mode = "watchdog" if self.watchdog_tripped else self.state.mode
        behaviour = None
        if self.behaviour is not None:
            try:
                behaviour = plain_json(telemetry_of(self.behaviour, self.robot_id))
            except BehaviourError as err:
                self.behaviour_failed(err)
        message = telemetry_message(
            step=self.state.seq, mode=mode, behaviour=behaviour, loop=self.stats.as_dict(),
            battery_v=self.driver.battery_v(), clock_s=round(self.clock.now(), 6),
            frames_lost=self.state.frames_lost, frames_bad=self.link.bad, unsent=self.link.unsent,
            inbox_dropped=self.state.inbox_dropped, run_id=self.run.get("run_id") if self.run else None,
            driver=self.driver_name())
        if self.error:
            message["error"] = error_for_the_hub(self.error)
        if self.run is None and self.error and self.refused_run_id is not None:
            message["refused_run_id"] = self.refused_run_id     # `ctl start` waits for this answer
        try:
            data = self.link.encode(message)
        except ProtocolError as err:       # too large, not JSON, or a field the hub drops: say so instead
            where = f"{err.field.replace('telemetry.', '', 1)}: " if err.field.startswith("telemetry.") else ""
            self.error = f"telemetry() cannot be sent: {where}{err.problem}"
            message.update(behaviour=None, error=error_for_the_hub(self.error))
            data = self.link.encode(message)
        self.link.send_encoded(data)

    # --- signals ------------------------------------------------------------------------------------------
    def _install_signal_handlers(self) -> List[Any]:
        def request_stop(signum, frame):
            # The loop wakes within 50 ms and stops the wheels on its way out (see serve); stopping here
            # could interrupt the driver or the socket in the middle of a call, and so could a log line.
            self.stop_requested = True
            self.stop_signal = signum

        previous = []
        for sig in stop_signals():          # each ends the agent as Ctrl-C does: wheels stopped, hub told
            try:
                previous.append((sig, signal.signal(sig, request_stop)))
            except ValueError:              # not the main thread (tests run agents in threads too)
                pass
        return previous

    @staticmethod
    def _restore_signal_handlers(previous: List[Any]) -> None:
        for sig, handler in previous:
            signal.signal(sig, handler)


def error_for_the_hub(error: str) -> str:
    """``error`` cut to the protocol's TEXT_MAX_CHARS in its middle, not at its end: the end says where and when
    (``at wander.py:5 (at t = 0.0 s)``), and a long radio-payload error lost it in SIL's account of the crash."""
    if len(error) <= TEXT_MAX_CHARS:
        return error
    keep_end = 80
    return error[:TEXT_MAX_CHARS - keep_end - 5] + " ... " + error[-keep_end:]
