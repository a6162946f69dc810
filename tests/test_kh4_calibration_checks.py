"""IR calibration files that load but would make a robot misread its surroundings (onboard/drivers/calibration.py)."""
from pathlib import Path

import pytest

from onboard.config import ConfigError
from onboard.drivers.calibration import load_calibration

LINEAR = "  - {ambient: 60, touch: 980}\n"


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "kh4-3.yaml"
    path.write_text(text)
    return path


def test_a_table_whose_readings_fall_as_the_raw_count_rises_is_refused(tmp_path):
    """A larger raw count is a nearer obstacle, so the linear form refuses touch <= ambient; a table with its
    readings the wrong way round ([[10, 1.0], [100, 0.0]], pairs swapped when written by hand) loaded, and the
    sensor read 'touching' with nothing near and 'nothing' when touching."""
    path = write(tmp_path, "proximity:\n  - {points: [[10, 1.0], [100, 0.0]]}\n" + LINEAR * 7)
    with pytest.raises(ConfigError, match=r"readings must not decrease .*\(got 0 after 1\)") as caught:
        load_calibration(path)
    assert caught.value.field == f"{path}: proximity[0].points[1][1]"


def test_a_flat_table_still_loads_for_a_dead_sensor(tmp_path):
    """A sensor that is dead is read as 0 with a flat table: equal readings are not a decrease."""
    path = write(tmp_path, "proximity:\n  - {points: [[0, 0.0], [1023, 0.0]]}\n" + LINEAR * 7)
    assert load_calibration(path).normalise([1023] * 8)[0] == 0.0


@pytest.mark.parametrize("robot", ["-1", "1000000"])
def test_a_robot_id_no_agent_can_have_is_refused(tmp_path, robot):
    """`robot: -1` loaded, and an agent then warned that the file was measured on robot -1."""
    path = write(tmp_path, f"robot: {robot}\nproximity:\n" + LINEAR * 8)
    with pytest.raises(ConfigError, match="must be") as caught:
        load_calibration(path)
    assert caught.value.field == f"{path}: robot"
