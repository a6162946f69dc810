"""An agent of `khepri sil` that something else stopped with a signal (a `kill` of its pid, a Ctrl-C that reached
the agents but not sil): sil's error said only `agent 3 exited with code 0`, a crash without a cause; the agent's
log says which signal it left on, and so does the error now."""
from types import SimpleNamespace

from hub.sil import SilSession
from hub.sil_agents import signal_it_left_on


def _session(tmp_path, logs, codes):
    (tmp_path / "agents").mkdir()
    for index, text in logs.items():
        (tmp_path / "agents" / f"agent-{index}.log").write_text(text)
    agents = [SimpleNamespace(poll=lambda code=code: code, returncode=code) for code in codes]
    return SimpleNamespace(agents=agents, out=tmp_path, _crash_line=lambda index: "")


def test_an_agent_that_left_on_a_signal_is_said_to_have_been_sent_it(tmp_path):
    session = _session(tmp_path, {0: "agent 0: run 1: transport\n",
                                   1: "agent 1: run 1: transport\nagent 1: SIGTERM: wheels stopped, leaving\n"},
                       [None, 0])
    assert signal_it_left_on(tmp_path, 1) == "SIGTERM" and signal_it_left_on(tmp_path, 0) == ""
    assert SilSession._dead_agent(session) == ("agent 1 exited with code 0: it was sent SIGTERM (not by khepri sil), "
                                               "stopped its wheels and left")


def test_an_agent_that_left_without_saying_why_keeps_its_exit_code_alone(tmp_path):
    session = _session(tmp_path, {0: "agent 0: SIGINTERESTING: not the line\n"}, [-9])
    assert signal_it_left_on(tmp_path, 0) == ""
    assert SilSession._dead_agent(session) == "agent 0 was killed by SIGKILL (exit code -9)"
