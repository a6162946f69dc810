import signal
import sys

import pytest

from sim_backend.scenario import parse_scenario


def pytest_configure(config):
    """A shell that starts the suite in the background (`make test &`, nohup, some CI runners) makes it ignore
    SIGINT, and so every process it starts. The Ctrl-C tests send SIGINT to this process and to hubs and
    agents: give it Python's own handler, as a terminal's foreground job has (children get the default)."""
    config.addinivalue_line("markers", "ipv6_loopback: needs the IPv6 loopback (::1); skipped where there is none")
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_collection_modifyitems(config, items):
    needing = [item for item in items if item.get_closest_marker("ipv6_loopback")]
    if needing and not ipv6_loopback_available():
        for item in needing:
            item.add_marker(pytest.mark.skip(reason="this machine has no IPv6 loopback"))


def ipv6_loopback_available() -> bool:
    import zmq

    probe = zmq.Context.instance().socket(zmq.ROUTER)
    probe.ipv6 = True
    try:
        probe.bind("tcp://[::1]:*")
        return True
    except zmq.ZMQError:
        return False
    finally:
        probe.close(0)


@pytest.fixture
def make_scenario():
    """Build a validated scenario from a partial mapping (behaviour defaults to aggregate)."""

    def build(**data):
        data.setdefault("behaviour", "aggregate")
        data.setdefault("name", "test")
        return parse_scenario(data)

    return build


@pytest.fixture(autouse=True, scope="session")
def hangup_as_a_terminal_would():
    """`nohup make test` starts the suite with SIGHUP ignored, and every hub and agent a test starts inherits
    that: they keep running on SIGHUP, as they should under nohup, and the tests of what a closed terminal does
    failed. The tests of nohup itself ignore it in their child explicitly."""
    previous = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    yield
    signal.signal(signal.SIGHUP, previous)


@pytest.fixture(autouse=True)
def restore_behaviour_registry():
    """Behaviours and evaluators that a test registers (a user's module it imports) do not outlive it: other
    tests list the known behaviours, and look evaluators up by the behaviour's name. A test module registers
    nothing as it is imported (tests/test_suite_isolation.py): what it needs, a fixture registers."""
    from onboard import behaviour
    from sim_backend import metrics

    behaviour.behaviour_names()          # the built-ins first: they register once per process, when imported
    metrics.evaluator_for("transport")   # the same for the built-in evaluators
    before, evaluators = dict(behaviour._REGISTRY), dict(metrics._EVALUATORS)
    yield
    behaviour._REGISTRY.clear()
    behaviour._REGISTRY.update(before)
    metrics._EVALUATORS.clear()
    metrics._EVALUATORS.update(evaluators)


@pytest.fixture
def user_behaviour(tmp_path, monkeypatch):
    """``install(module, code, scenario_template)``: a user's behaviour module written into a fresh folder, the
    test run from there; returns ``scenario(bug)``, which writes ``<bug>.yaml`` from the template (``{bug}``
    filled in) and gives its name. The module is forgotten afterwards, so the next test's import registers it
    again."""
    installed = []

    def install(module: str, code: str, template: str):
        (tmp_path / f"{module}.py").write_text(code)
        monkeypatch.chdir(tmp_path)
        installed.append(module)

        def scenario(bug: str) -> str:
            (tmp_path / f"{bug}.yaml").write_text(template.format(bug=bug))
            return f"{bug}.yaml"

        return scenario

    yield install
    for module in installed:
        sys.modules.pop(module, None)


@pytest.fixture
def first_waiting_line():
    """The first line an agent on a given HubLink says while the hub sends it nothing (within 10 s)."""
    import time

    from onboard.agent.loop import Agent
    from onboard.drivers.sim import SimDriver

    def waiting_line(link) -> str:
        lines: list = []
        agent = Agent(link.robot_id, link,
                      lambda a: SimDriver(link.send, lambda: a.state.sim), log=lines.append)
        started = time.monotonic()
        agent.serve(should_stop=lambda: any("no frame from the hub" in line for line in lines)
                    or time.monotonic() - started > 10.0)
        link.close()
        waiting = [line for line in lines if "no frame from the hub" in line]
        assert waiting, lines
        return waiting[0]

    return waiting_line

