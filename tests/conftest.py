import pytest

from sim_backend.scenario import parse_scenario


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
