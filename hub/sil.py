"""Software in the loop: the hub's ``sim`` source plus one real agent process per robot, over loopback
ZeroMQ with CURVE (throw-away keys), evaluated exactly like ``khepri sim run``.

Lockstep (default): physics advances one control step when every agent answered, so a 250 s run takes
seconds. ``realtime``: the hub's normal loop paces physics by the wall clock and agents tick on their own.
"""
from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional

from onboard.behaviour import build_params, get_behaviour
from onboard.config import ConfigError
from sim_backend.metrics import EvaluatorError, evaluator_call, make_evaluator, merge_result
from sim_backend.runner import mission_params
from sim_backend.scenario import Scenario

from .config import DEFAULT_WATCHDOG_S, min_watchdog_s, parse_config
from .factory import build_hub, run_template
from .harness import spawn_agent, stop_processes
from .keyfiles import init_keys
from .lockstep import UNRESPONSIVE_AFTER_STEPS, Lockstep
from .runner import print_now
from .sil_agents import (
    KEY_FOLDER_PREFIX,
    agent_log_line,
    agent_python_text,
    agent_traceback,
    exit_text,
    let_leaving_agents_exit,
    remove_stale_key_folders,
    signal_it_left_on,
    slow_step_warnings,
    stop_failure,
)
from .sil_report import SilRecording, agents_total, sil_figures
from .sim_source import not_simulated_here, refuse_agent_restarts

CONNECT_TIMEOUT_S = 60.0


@dataclass
class SilOptions:
    seed: Optional[int] = None
    time_limit_s: Optional[float] = None
    realtime: bool = False
    record: bool = True
    plot: bool = True
    step_timeout_s: float = 2.0
    imports: List[str] = field(default_factory=list)    # the user's behaviour modules (--import), for the agents
    log_to_console: bool = False
    scenario_ref: Optional[str] = None     # the scenario as given (its file), for errors; None: its name
    agent_python: Optional[str] = None     # the agents' interpreter (--agent-python); None: this one
    agent_python_version: Optional[str] = None     # its version, as check_agent_python found it
    settings: Dict[str, Any] = field(default_factory=dict)    # --set values the scenario was loaded with


def run_sil(scenario: Scenario, out: Path, options: SilOptions) -> Dict[str, Any]:
    from sim_backend.outputs import write_run

    out.mkdir(parents=True, exist_ok=True)
    seed = scenario.seed if options.seed is None else options.seed
    # The time limit the run gets, as `sim run` does: the warnings (a fault that never fires) go by it.
    scenario = scenario.with_overrides(seed=seed).with_time_limit(options.time_limit_s)
    limit = scenario.time_limit_s
    refuse_before_starting(scenario, options.scenario_ref)     # before the folder's last run is cleared away
    # backslashreplace: a line quoting a robot's text with a lone surrogate is written escaped, not a crash
    hub_log = open(out / "hub.log", "w", encoding="utf-8", errors="backslashreplace")   # noqa: SIM115 - closed below

    def log(line: str) -> None:
        hub_log.write(line + "\n")
        hub_log.flush()
        if options.log_to_console:
            print_now(line)      # a closed terminal drops the line, and does not skip closing the hub and agents

    # The folder is this run's: an earlier run's log or results would pass for this one's should it end
    # early (and the hub never writes over a log), so they go, also with --no-record.
    for name in ("hub.mcap", "result.json", "trajectory.npz", "trajectory.png"):
        (out / name).unlink(missing_ok=True)
    for old_log in (out / "agents").glob("agent-*.log"):   # a run with more robots left more of them
        old_log.unlink(missing_ok=True)
    remove_stale_key_folders()
    with tempfile.TemporaryDirectory(prefix=f"{KEY_FOLDER_PREFIX}{os.getpid()}-") as key_dir:
        keys = Path(key_dir)
        init_keys(keys, list(range(scenario.robots.count)), ["sil"])
        config = parse_config(sil_config(scenario, options, {"keys": str(keys)},
                                         str(out / "hub.mcap") if options.record else None))
        hub = build_hub(config, log=log, scenario=scenario)
        agents: List[subprocess.Popen] = []
        session: Optional[SilSession] = None
        try:
            hub.bind()
            agents = spawn_agents(hub.endpoints["robots"], keys, scenario.robots.count, out, options)
            session = SilSession(hub, scenario, agents, options, limit, out)
            logged_by_hub = set(not_simulated_here(scenario))      # its sim source said those as it started
            for warning in session.warnings:
                print(f"khepri: warning: {warning}", file=sys.stderr)
                if warning not in logged_by_hub:
                    log(f"hub: warning: {warning}")
            result = session.run()
        finally:
            # A Ctrl-C from the terminal reaches the agents too; a `kill` or a closed session reaches sil alone
            interrupt = sys.exc_info()[1] if session is None or session.interrupt is None else session.interrupt
            ctrl_c = isinstance(interrupt, KeyboardInterrupt) and getattr(interrupt, "how", "Ctrl-C") == "Ctrl-C"
            let_leaving_agents_exit(hub, agents, ctrl_c)
            stop_processes(agents)        # SIGTERM: each agent stops its wheels and exits
            hub.close()
            hub_log.close()
    result["sil"]["agent_exit_codes"] = [a.returncode for a in agents]
    for warning in slow_step_warnings(out, len(agents)):       # the logs are whole once the agents have exited
        print(f"khepri: warning: {warning}", file=sys.stderr)
        result["warnings"] = [*result.get("warnings", []), warning]
    result["sil"]["agent_python"] = agent_python_text(options.agent_python, options.agent_python_version)
    stop_error = stop_failure(out, len(agents))
    if stop_error and "error" not in result:     # the run itself went well; the behaviour's stop() did not
        result["error"] = stop_error
    result["sil"]["log"] = str(out / "hub.mcap") if options.record else None
    if options.settings:
        result["settings"] = options.settings
    write_run(session.recording, result, out, plot=options.plot)
    return result


def sil_config(scenario: Scenario, options: SilOptions, security: Dict[str, Any], record: Optional[str]) -> dict:
    return {
        # One run, on the world the session's evaluator and recording hold: never rebuilt under them.
        "source": {"type": "sim", "lockstep": not options.realtime, "reset_each_run": False},
        "network": {"bind": "127.0.0.1", "robot_port": 0, "control_port": 0},
        "security": security,
        "record": record,
        # The agents' telemetry comes once per control step: a slow scenario needs a longer watchdog.
        "watchdog_s": max(DEFAULT_WATCHDOG_S, min_watchdog_s(scenario.physics.control_hz)),
    }


def refuse_before_starting(scenario: Scenario, scenario_ref: Optional[str] = None) -> None:
    """What the hub would refuse in this scenario (agent restarts, a transport without an object, bad run
    params, a loop too slow for a hub), said before anything in --out is touched: a refused scenario cleared the
    last run's results."""
    refuse_agent_restarts(scenario)
    run_template(parse_config(sil_config(scenario, SilOptions(), {"insecure": True}, None)), scenario, scenario_ref)


def spawn_agents(endpoint: str, keys: Path, count: int, out: Path, options: SilOptions) -> List[subprocess.Popen]:
    """One agent process per robot, with ``options.agent_python``; each imports the user's behaviour modules, as
    `khepri --import` did here."""
    logs = out / "agents"
    logs.mkdir(exist_ok=True)
    extra = [word for name in options.imports for word in ("--import", name)]
    return [spawn_agent(endpoint, i, logs / f"agent-{i}.log", keys=keys, extra=extra, python=options.agent_python)
            for i in range(count)]


STUCK_STEP_NOTE = "the behaviour's step() has run for "    # the agent's step watchdog, once per stuck step


def stuck_step_account(robot, said: str) -> str:
    """The agent's note on its stuck step, with how long the step has run by now. The note gives the time
    when the agent's watchdog tripped (a quarter of a second in), said once: the step began when the agent
    got the first frame it left unanswered, so the hub counts from when it sent that frame."""
    _, _, rest = said.partition(" s: ")          # "0.26 s: wheels stopped (...)" -> "wheels stopped (...)"
    if robot.silent_since == -math.inf or not rest:
        return STUCK_STEP_NOTE + said
    running_s = time.monotonic() - robot.silent_since
    return f"{STUCK_STEP_NOTE}{running_s:.1f} s, since t = {robot.silent_since_clock_s:.1f} s: {rest}"


class AgentError(RuntimeError):
    """An agent reported that it cannot run (its telemetry's ``error``)."""


class SilSession:
    def __init__(self, hub, scenario: Scenario, agents, options: SilOptions, limit_s: float, out: Path):
        self.hub, self.scenario, self.agents, self.options, self.out = hub, scenario, agents, options, out
        self.source = hub.source
        self.limit_s = limit_s
        self.evaluator = make_evaluator(scenario.behaviour, scenario, self.source.world)
        if hub.progress is not None:      # the hub's console and log tell the run's progress from this one
            hub.progress.attach(self.evaluator)
        behaviour_cls = get_behaviour(scenario.behaviour)       # the agents build these same params
        self.warnings = evaluator_call(self.evaluator, "warnings",
                                       build_params(behaviour_cls, mission_params(behaviour_cls, scenario)))
        self.warnings = [*self.warnings, *not_simulated_here(scenario)]
        self.recording = SilRecording(scenario, self.source.world)
        self.round_trips: List[float] = []
        self.missing_answers = 0
        self.stop_reason = "time limit"
        self.interrupt: Optional[KeyboardInterrupt] = None      # what ended the run early, if it was interrupted

    def run(self) -> Dict[str, Any]:
        self.hub.expect_frames_from(math.inf)      # physics starts once the agents are there (_run_realtime)
        lockstep = Lockstep(self.hub, self.options.step_timeout_s)
        count = len(self.agents)
        problem = lockstep.wait_for(lambda: self._connected() == count or self._dead_agent() is not None,
                                    CONNECT_TIMEOUT_S, f"{count} agents to connect")
        problem = problem or self._dead_agent()
        if problem:
            raise ConfigError("sil", f"{problem}; see the agent logs in {self.out / 'agents'}")
        self.hub.control.execute("start", "sil")
        # An agent whose behaviour's __init__ raised exits without acknowledging: not a 10 s wait for it.
        lockstep.wait_for(lambda: all(r.pending is None for r in self.hub.robots.values())
                          or self._dead_agent() is not None, 10.0, "start acks")
        started = time.perf_counter()
        error = None
        try:
            if self.options.realtime:
                self._run_realtime()
            else:
                self._run_lockstep(lockstep)
        except Exception as exc:   # a crashed run is reported, not lost (as in `khepri sim run`)
            what = str(exc) if isinstance(exc, EvaluatorError) else f"{type(exc).__name__}: {exc}"
            error = str(exc) if isinstance(exc, AgentError) else f"{what} (at t = {self.source.time_s:.1f} s)"
            self.stop_reason = "crashed"
        except KeyboardInterrupt as interrupt:  # Ctrl-C or SIGTERM: what was recorded is written, as `sim run` does
            self.interrupt = interrupt
            error = f"interrupted ({getattr(interrupt, 'how', 'Ctrl-C')}) (at t = {self.source.time_s:.1f} s)"
            self.stop_reason = "interrupted"
        wall = time.perf_counter() - started
        # 'crashed: agent 0 stopped answering ...'; 'interrupted (Ctrl-C) ...' says why already
        note = None if error is None else error if error.startswith(self.stop_reason) else \
            f"{self.stop_reason}: {error}"
        self.hub.control.execute("stop", "sil", note=note)
        return self._result(wall, lockstep, error)

    def _connected(self) -> int:
        return sum(1 for r in self.hub.robots.values() if r.routing is not None)

    def _dead_agent(self) -> Optional[str]:
        for i, agent in enumerate(self.agents):
            if agent.poll() is not None:
                why = self._crash_line(i)
                if why:
                    return f"agent {i}: behaviour crashed: {why}; the agent exited with code {agent.returncode}"
                signal_name = signal_it_left_on(self.out, i)
                if signal_name:      # 'exited with code 0' alone read as a crash without a cause
                    return (f"agent {i} {exit_text(agent.returncode)}: it was sent {signal_name} (not by khepri "
                            "sil), stopped its wheels and left")
                return f"agent {i} {exit_text(agent.returncode)}"
        return None

    def _check_answering(self, missing: List[int]) -> None:
        """An agent alive but silent for UNRESPONSIVE_AFTER_STEPS steps in a row ends the run as crashed: in
        lockstep every agent answers every frame, so one that does not is stuck (a step() that never returns,
        say), and the run would otherwise go on to its time limit as if nothing were wrong."""
        for rid in missing:
            robot = self.hub.robots[rid]
            if robot.unresponsive_steps >= UNRESPONSIVE_AFTER_STEPS and rid not in self.hub.killed:
                said = agent_log_line(self.out, rid, f"agent {rid}: {STUCK_STEP_NOTE}")
                raise AgentError(f"agent {rid} stopped answering ({robot.unresponsive_steps} frames in a row, "
                                 f"{self.options.step_timeout_s:g} s each)"
                                 + (f": {stuck_step_account(robot, said)}" if said else "")
                                 + f"; its log is in {self.out / 'agents'}")

    def _check_silence(self) -> None:
        """In real time, an agent alive but silent as long as lockstep waits for one (UNRESPONSIVE_AFTER_STEPS
        frames of step_timeout_s) is stuck too: the run went on to its time limit and sil exited 0."""
        limit_s = UNRESPONSIVE_AFTER_STEPS * self.options.step_timeout_s
        now = time.monotonic()
        for rid, robot in self.hub.robots.items():
            silent_s = now - robot.last_uplink
            if robot.routing is None or rid in self.hub.killed or silent_s < limit_s:
                continue
            said = agent_log_line(self.out, rid, f"agent {rid}: {STUCK_STEP_NOTE}")
            account = f": {STUCK_STEP_NOTE}{said}" if said else ""
            raise AgentError(f"agent {rid} stopped answering ({silent_s:.1f} s without a message){account}; its log "
                             f"is in {self.out / 'agents'}")

    def _whole_error(self, index: int, error: str) -> str:
        """Telemetry's ``error`` is cut in the middle to fit the protocol (``... ``): the agent's log has it whole."""
        head, cut, _ = error.partition(" ... ")
        rest = agent_log_line(self.out, index, f"agent {index}: {head}") if cut else ""
        return head + rest if rest else error

    def _crash_line(self, index: int) -> str:
        """The agent's own account of its crash (``behaviour crashed: ...``) from its log, if it wrote one."""
        return agent_log_line(self.out, index, f"agent {index}: behaviour crashed: ")

    def _run_lockstep(self, lockstep: Lockstep) -> None:
        period = self.source.control_period
        steps = int(math.ceil(self.limit_s / period - 1e-9))
        for _ in range(steps):
            report = lockstep.step()
            self.round_trips.extend(report.round_trip_s)
            self.missing_answers += len(report.missing)
            self._check_answering(report.missing)
            reason = self._observe(report.time_s)
            if reason:
                self.stop_reason = reason
                return
            lockstep.advance()

    def _run_realtime(self) -> None:
        self.hub.expect_frames_from(time.monotonic())
        period = self.source.control_period
        observed = -1

        def should_stop() -> bool:
            nonlocal observed
            step = self.source.control_steps_done()
            # Step k begins at k * period: the step that would begin at the time limit is not run (as in
            # lockstep and `khepri sim run`), so that sim_time_s is the limit, not one period past it.
            if step * period >= self.limit_s - 1e-9:
                return True
            if step != observed and self.hub.clock_s is not None:
                observed = step
                self._check_silence()
                reason = self._observe(step * period)
                if reason:
                    self.stop_reason = reason
                    return True
            return self.source.time_s >= self.limit_s - 1e-9

        self.hub.serve(should_stop)

    def _observe(self, t: float) -> Optional[str]:
        """Evaluate one control step from the agents' telemetry; the reason to stop the run, if there is one.
        An agent that could not start the run (say, a behaviour it cannot import) ends the run as crashed:
        without it the run would go on to its time limit with that robot standing still."""
        for rid, robot in self.hub.robots.items():
            error = (robot.telemetry or {}).get("error")
            if error:
                raise AgentError(f"agent {rid}: {self._whole_error(rid, error)}")
        dead = self._dead_agent()
        if dead:
            raise AgentError(f"{dead} (its log is in {self.out / 'agents'})")
        alive = self.source.world.alive()
        telemetry = [self._behaviour_telemetry(i) if alive[i] else None for i in range(len(alive))]
        evaluator_call(self.evaluator, "on_step", t, telemetry)
        self.recording.add(t, self.source.world, evaluator_call(self.evaluator, "centroid_estimate", telemetry))
        live = [tel for tel, a in zip(telemetry, alive) if a]
        if not live:
            return "every robot failed"
        return "behaviour finished" if all(tel is not None and tel.get("finished") for tel in live) else None

    def _behaviour_telemetry(self, index: int) -> Optional[Dict[str, Any]]:
        telemetry = self.hub.robots[index].telemetry
        return None if telemetry is None else telemetry.get("behaviour")

    def _radio_counts(self) -> Dict[str, int]:
        """The simulator's radio counts (``RadioNetwork.stats``) from the hub's relay and the agents' inboxes:
        a message is lost to overflow in the hub's queue or in a full inbox on the robot."""
        relay = self.hub.relay.stats
        overflowed = agents_total(self.hub, "inbox_dropped")
        return {"sent": relay.sent, "delivered": relay.delivered - overflowed, "dropped": relay.dropped_random,
                "dropped_overflow": relay.dropped_overflow + overflowed}

    def _result(self, wall: float, lockstep: Lockstep, error: Optional[str]) -> Dict[str, Any]:
        sim_time = self.recording.t[-1] + self.source.control_period if self.recording.t else 0.0
        result: Dict[str, Any] = {
            "scenario": self.scenario.name, "seed": self.scenario.seed, "robots": len(self.agents),
            "behaviour": self.scenario.behaviour, "sim_time_s": round(sim_time, 6), "wall_time_s": round(wall, 3),
            "real_time_factor": round(sim_time / wall, 2) if wall > 0 else None, "stop_reason": self.stop_reason,
            "radio": self._radio_counts(),
        }
        if self.warnings:
            result["warnings"] = list(self.warnings)
        failure = merge_result(self.evaluator, result, error)     # both kept when both failed, as in sim run
        if failure is not None:
            error = str(failure)
        # As sim run's: null for a robot a scenario fault killed, whatever its agent said last.
        alive = self.source.world.alive()
        result["telemetry"] = [self._behaviour_telemetry(i) if alive[i] else None for i in range(len(self.agents))]
        result["sil"] = sil_figures(self.hub, lockstep, self.round_trips, self.missing_answers,
                                    not self.options.realtime)
        if error:
            result["error"] = error
        trace = self._crash_traceback(error or "") if self.stop_reason == "crashed" else None
        if trace:
            result["traceback"] = trace        # as `sim run` writes it; the agent's log has it too
        return result

    def _crash_traceback(self, error: str) -> Optional[List[str]]:
        """The traceback of the agent the error names (``agent 2: behaviour crashed: ...``); the first found
        only when it names none (an evaluator's error, say)."""
        named = re.match(r"agent (\d+)\b", error)
        for i in ([int(named.group(1))] if named else range(len(self.agents))):
            trace = agent_traceback(self.out, i)
            if trace:
                return trace
        return None
