import signal

import pytest

from sim_backend.scenario import parse_scenario


def pytest_configure(config):
    """A shell that starts the suite in the background (`make test &`, nohup, some CI runners) makes it ignore
    SIGINT, and so every process it starts. The Ctrl-C tests send SIGINT to this process and to hubs and
    agents: give it Python's own handler, as a terminal's foreground job has (children get the default)."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def make_scenario():
    """Build a validated scenario from a partial mapping (behaviour defaults to aggregate)."""

    def build(**data):
        data.setdefault("behaviour", "aggregate")
        data.setdefault("name", "test")
        return parse_scenario(data)

    return build


@pytest.fixture(autouse=True)
def restore_behaviour_registry():
    """Behaviours that a test registers (a user's module it imports) do not outlive it: other tests list the
    known behaviours."""
    from onboard import behaviour

    behaviour.behaviour_names()          # the built-ins first: they register once per process, when imported
    before = dict(behaviour._REGISTRY)
    yield
    behaviour._REGISTRY.clear()
    behaviour._REGISTRY.update(before)
