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
