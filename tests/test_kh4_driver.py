"""The KheperaIV driver against a stand-in libkhepera.so compiled from tests/kh4_stub/libkhepera_stub.c.

The stub has libkhepera's function names and C prototypes, logs every call with its arguments and returns
scripted sensor values, so these tests check what would reach a robot: ctypes signatures, hardware units,
the IR index mapping, calibration, encoder conversion, and that the wheels are stopped on every way out.
"""
import io
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Dict, List, Tuple

import pytest

from onboard.config import ConfigError
from onboard.drivers.calibration import load_calibration
from onboard.drivers.kh4 import SENSOR_FAILURES_TOLERATED, KheperaIV, LibkheperaError
from onboard.drivers.kh4_guard import guard
from onboard.hal import WheelOdometry

ROOT = Path(__file__).resolve().parents[1]
STUB_SOURCE = ROOT / "tests" / "kh4_stub" / "libkhepera_stub.c"
HAL_DIRECTIONS = ("front", "front-left", "left", "back-left", "back", "back-right", "right", "front-right")
# Where each sensor's registers sit in kh4_proximity_ir's buffer (kb_khepera4.c, I2C_IR_DIST_* 0x58..0x67).
HARDWARE_BUFFER_SLOT = {"back-left": 0, "left": 1, "front-left": 2, "front": 3, "front-right": 4, "right": 5,
                        "back-right": 6, "back": 7}

Call = Tuple[str, Dict[str, str]]


def compile_stub(out_dir: Path, *defines: str) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc is not installed: cannot build the stand-in libkhepera.so")
    library = out_dir / "libkhepera.so"
    out_dir.mkdir(parents=True, exist_ok=True)
    subprocess.run(["gcc", "-shared", "-fPIC", "-Wall", "-Werror", *(f"-D{d}" for d in defines),
                    "-o", str(library), str(STUB_SOURCE)], check=True)
    return library


@pytest.fixture(scope="module")
def stub_library(tmp_path_factory) -> Path:
    return compile_stub(tmp_path_factory.mktemp("stub"))


@pytest.fixture
def stub_log(tmp_path, monkeypatch) -> Path:
    """A fresh call log and neutral scripted values (os.environ changes reach the C library's getenv)."""
    log = tmp_path / "calls.log"
    monkeypatch.setenv("KH4_STUB_LOG", str(log))
    for name in ("KH4_STUB_IR", "KH4_STUB_POSITION", "KH4_STUB_BATTERY", "KH4_STUB_FAIL", "KH4_STUB_FAIL_TIMES",
                 "KH4_STUB_HANG", "KH4_STUB_HANG_AFTER", "KHEPRI_LIBKHEPERA", "KHEPRI_KH4_CALIBRATION"):
        monkeypatch.delenv(name, raising=False)
    return log


def calls(log: Path) -> List[Call]:
    parsed = []
    for line in log.read_text().splitlines():
        name, *pairs = line.split()
        parsed.append((name, dict(pair.split("=", 1) for pair in pairs)))
    return parsed


def speed_commands(log: Path) -> List[Tuple[int, int]]:
    return [(int(a["left"]), int(a["right"])) for name, a in calls(log) if name == "kh4_set_speed"]


def write_yaml(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


# --- opening, units, signatures -----------------------------------------------------------------------------
def test_opening_initialises_the_library_and_drives_in_speed_profile_mode(stub_library, stub_log):
    driver = KheperaIV(library_path=str(stub_library))
    names = [name for name, _ in calls(stub_log)]
    assert names[:2] == ["kh4_init", "knet_open"]
    assert calls(stub_log)[0][1] == {"argc": "0", "argv": "null"}
    assert calls(stub_log)[1][1] == {"device": "Khepera4:dsPic", "bus": "0", "argc": "0", "argv": "null"}
    assert ("kh4_SetMode", {"mode": "2", "dev": "ok"}) in calls(stub_log)
    # every function got the very handle knet_open returned, not a truncated pointer
    assert all(args.get("dev", "ok") == "ok" for _, args in calls(stub_log))
    driver.close()


def test_wheel_speeds_in_m_s_reach_kh4_set_speed_in_hardware_units(stub_library, stub_log):
    with KheperaIV(library_path=str(stub_library)) as driver:
        driver.set_wheel_speeds(0.1, -0.05)
        driver.set_wheel_speeds(0.0, 0.2034)
    # 100 mm/s / 0.6781 = 147.5 -> 147; -50 / 0.6781 = -73.7 -> -74; 203.4 / 0.6781 = 299.96 -> 300
    assert speed_commands(stub_log)[:2] == [(147, -74), (0, 300)]


def test_speeds_beyond_the_limit_are_scaled_together_so_the_turn_is_kept(stub_library, stub_log):
    with KheperaIV(library_path=str(stub_library)) as driver:
        driver.set_wheel_speeds(1.62, 0.81)           # twice the KheperaIV's 0.81 m/s
        driver.set_wheel_speeds(-5.0, -5.0)
    with KheperaIV(library_path=str(stub_library), max_wheel_speed_m_s=0.2) as slow:
        slow.set_wheel_speeds(0.4, -0.1)
    commands = speed_commands(stub_log)
    assert commands[0] == (1194, 597)                 # 810 mm/s is 1194.5 units: never past the limit
    assert commands[1] == (-1194, -1194)
    assert (294, -74) in commands                     # 0.2 and -0.05 m/s


def test_a_speed_that_is_not_a_number_stops_the_wheels_and_names_the_wheel(stub_library, stub_log):
    with KheperaIV(library_path=str(stub_library)) as driver:
        driver.set_wheel_speeds(0.1, 0.1)
        with pytest.raises(ValueError, match="right_m_s"):
            driver.set_wheel_speeds(0.1, float("nan"))
        assert speed_commands(stub_log) == [(147, 147), (0, 0)]
        with pytest.raises(ValueError, match="left_m_s"):
            driver.set_wheel_speeds("fast", 0.1)


# --- IR ring ------------------------------------------------------------------------------------------------
def hardware_ir(values_by_direction: Dict[str, int], ground: Tuple[int, ...] = (11, 22, 33, 44)) -> str:
    ring = [0] * 8
    for direction, raw in values_by_direction.items():
        ring[HARDWARE_BUFFER_SLOT[direction]] = raw
    return " ".join(str(v) for v in ring + list(ground))


def test_ir_values_come_back_in_hal_order_forward_then_counter_clockwise(stub_library, stub_log, monkeypatch):
    distinct = {direction: 100 + 37 * i for i, direction in enumerate(HARDWARE_BUFFER_SLOT)}
    distinct["front"] = 1000                          # > 255: both bytes of the little-endian pair matter
    monkeypatch.setenv("KH4_STUB_IR", hardware_ir(distinct))
    with KheperaIV(library_path=str(stub_library)) as driver:
        raw = driver.raw_proximity()
    assert raw == [distinct[direction] for direction in HAL_DIRECTIONS]


def test_without_a_calibration_file_readings_are_raw_over_1023_clipped(stub_library, stub_log, monkeypatch):
    raws = dict(zip(HAL_DIRECTIONS, (0, 1023, 512, 1100, 0, 0, 0, 0)))   # 1100: out of range, clips to 1
    monkeypatch.setenv("KH4_STUB_IR", hardware_ir(raws))
    with KheperaIV(library_path=str(stub_library)) as driver:
        values = driver.proximity()
    assert values == pytest.approx([0.0, 1.0, 512 / 1023, 1.0, 0.0, 0.0, 0.0, 0.0])


def test_a_calibration_file_normalises_each_hal_sensor_its_own_way(stub_library, stub_log, monkeypatch, tmp_path):
    calibration = write_yaml(tmp_path / "kh4-3.yaml", """\
        robot: 3
        notes: white foam, lab lights on
        proximity:
          - {ambient: 100, touch: 900}
          - {ambient: 100, touch: 900}
          - {ambient: 200, touch: 600}
          - {points: [[50, 0.0], [250, 0.5], [450, 1.0]]}
          - {ambient: 0, touch: 1023}
          - {ambient: 0, touch: 1023}
          - {ambient: 0, touch: 1023}
          - {ambient: 0, touch: 1023}
        """)
    raws = dict(zip(HAL_DIRECTIONS, (500, 50, 700, 150, 0, 0, 0, 0)))
    monkeypatch.setenv("KH4_STUB_IR", hardware_ir(raws))
    with KheperaIV(library_path=str(stub_library), calibration_path=calibration) as driver:
        values = driver.proximity()
    # front (500-100)/800; front-left below ambient -> 0; left above touch -> 1; back-left on the table
    assert values[:4] == pytest.approx([0.5, 0.0, 1.0, 0.25])


def test_the_calibration_path_can_come_from_the_environment(stub_library, stub_log, monkeypatch, tmp_path):
    calibration = write_yaml(tmp_path / "kh4-1.yaml", "proximity: " + str([{"ambient": 0, "touch": 100}] * 8))
    monkeypatch.setenv("KHEPRI_KH4_CALIBRATION", str(calibration))
    monkeypatch.setenv("KH4_STUB_IR", hardware_ir({"front": 50}))
    with KheperaIV(library_path=str(stub_library)) as driver:
        assert driver.proximity()[0] == pytest.approx(0.5)


@pytest.mark.parametrize("body, field, problem", [
    ("proximity: " + str([{"ambient": 0, "touch": 100}] * 7), "proximity", "must list 8 sensors"),
    ("proximity: " + str([{"ambient": 500, "touch": 400}] * 8), "proximity[0].touch", "must be > ambient"),
    ("proximity: " + str([{"ambient": 0}] * 8), "proximity[0].touch", "is required"),
    ("proximity: " + str([{"ambient": 0, "touch": 2000}] * 8), "proximity[0].touch", "must be <= 1023"),
    ("proximity: " + str([{"ambient": 0, "touch": 9, "points": [[0, 0], [9, 1]]}] * 8), "proximity[0]",
     "not both"),
    ("proximity: " + str([{"points": [[0, 0], [500, 0.5], [400, 1.0]]}] * 8), "proximity[0].points[2][0]",
     "must increase"),
    ("proximity: " + str([{"points": [[0, 0], [500, 1.5]]}] * 8), "proximity[0].points[1][1]", "must be <= 1"),
    ("proximity: " + str([{"gain": 2}] * 8), "proximity[0].gain", "unknown key"),
    ("robot: three\nproximity: []", "robot", "must be an integer"),
])
def test_a_bad_calibration_file_is_refused_naming_the_file_and_the_field(tmp_path, body, field, problem):
    path = write_yaml(tmp_path / "kh4-9.yaml", body)
    with pytest.raises(ConfigError, match=problem) as caught:
        load_calibration(path)
    assert caught.value.field == f"{path}: {field}"


def test_a_missing_or_unparsable_calibration_file_is_refused_before_the_robot_is_touched(
        stub_library, stub_log, tmp_path):
    with pytest.raises(ConfigError, match="no such file") as caught:
        KheperaIV(library_path=str(stub_library), calibration_path=tmp_path / "absent.yaml")
    assert "absent.yaml" in str(caught.value)
    broken = write_yaml(tmp_path / "broken.yaml", "proximity: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        KheperaIV(library_path=str(stub_library), calibration_path=broken)
    assert not stub_log.exists()


def test_the_agent_names_a_missing_calibration_file_once(stub_library, stub_log, tmp_path):
    """It said `--calibration: calibration file: no such file: ...`, the option and then the file's own label."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), KH4_STUB_LOG=str(stub_log))
    done = subprocess.run([sys.executable, "-m", "onboard.agent", "--id", "0", "--driver", "kh4", "--library",
                           str(stub_library), "--calibration", str(tmp_path / "absent.yaml"), "--hub",
                           "tcp://127.0.0.1:9"], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=30)
    assert done.returncode == 2, done.stderr
    assert f"agent: error: --calibration: no such file: {tmp_path / 'absent.yaml'}\n" in done.stderr, done.stderr
    assert not stub_log.exists()
    # A control character in the name is shown, not printed raw: "no such file: c.yaml" for c\x01.yaml, which
    # exists, read as nonsense.
    (tmp_path / "c.yaml").write_text("{}\n")
    done = subprocess.run([sys.executable, "-m", "onboard.agent", "--id", "0", "--driver", "kh4", "--library",
                           str(stub_library), "--calibration", "c\x01.yaml", "--hub", "tcp://127.0.0.1:9"],
                          env=env, cwd=tmp_path, capture_output=True, text=True, timeout=30)
    assert "agent: error: --calibration: no such file: c\\x01.yaml\n" in done.stderr, done.stderr


def test_a_calibration_file_nested_thousands_deep_is_refused_naming_it(stub_library, stub_log, tmp_path):
    """It gave "cannot open the KheperaIV: maximum recursion depth exceeded" (a RecursionError is a RuntimeError),
    as if the hardware had failed, and named no file."""
    for name, text in (("deep.json", "[" * 5000 + "]" * 5000), ("deep.yaml", "proximity: " + "[" * 5000 + "]" * 5000)):
        deep = write_yaml(tmp_path / name, text)
        with pytest.raises(ConfigError, match="nested too deeply") as caught:
            KheperaIV(library_path=str(stub_library), calibration_path=deep)
        assert caught.value.field == str(deep)
    assert not stub_log.exists()


# --- encoders and battery -----------------------------------------------------------------------------------
def test_encoders_give_signed_metres_per_wheel_since_the_driver_opened(stub_library, stub_log, monkeypatch):
    monkeypatch.setenv("KH4_STUB_POSITION", "5000 -3000")
    with KheperaIV(library_path=str(stub_library)) as driver:
        assert driver.encoders() == WheelOdometry(0.0, 0.0)
        # 147471 pulses x 0.006781 mm = 1.000 m forward on the left; 14747 back on the right = -0.1 m
        monkeypatch.setenv("KH4_STUB_POSITION", f"{5000 + 147471} {-3000 - 14747}")
        odometry = driver.encoders()
    assert odometry.left_m == pytest.approx(1.0, abs=1e-4)
    assert odometry.right_m == pytest.approx(-0.1, abs=1e-4)


def test_encoders_keep_counting_through_the_32_bit_wrap(stub_library, stub_log, monkeypatch):
    monkeypatch.setenv("KH4_STUB_POSITION", f"{2 ** 31 - 100} {-2 ** 31 + 100}")
    with KheperaIV(library_path=str(stub_library)) as driver:
        monkeypatch.setenv("KH4_STUB_POSITION", f"{-2 ** 31 + 100} {2 ** 31 - 100}")
        odometry = driver.encoders()
    assert odometry.left_m == pytest.approx(200 * 0.006781 / 1000)
    assert odometry.right_m == pytest.approx(-200 * 0.006781 / 1000)


def test_battery_voltage_is_read_when_the_library_offers_it(stub_library, stub_log, monkeypatch, tmp_path):
    monkeypatch.setenv("KH4_STUB_BATTERY", "760")
    with KheperaIV(library_path=str(stub_library)) as driver:
        assert driver.battery_v() == pytest.approx(760 * 0.00976)
    without_battery = compile_stub(tmp_path / "no-battery", "KH4_STUB_WITHOUT_BATTERY")
    with KheperaIV(library_path=str(without_battery)) as driver:
        assert driver.battery_v() is None


# --- errors -------------------------------------------------------------------------------------------------
def test_a_missing_library_names_its_path_and_how_to_set_it(stub_log, monkeypatch, tmp_path):
    absent = tmp_path / "nowhere" / "libkhepera.so"
    monkeypatch.setenv("KHEPRI_LIBKHEPERA", str(absent))
    with pytest.raises(LibkheperaError) as caught:     # a path given: that path (the agent names its option)
        KheperaIV()
    assert str(absent) in str(caught.value) and "pass --library" not in str(caught.value)
    monkeypatch.delenv("KHEPRI_LIBKHEPERA")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(LibkheperaError, match="pass --library PATH or set KHEPRI_LIBKHEPERA"):   # the default
        KheperaIV()


def test_a_bare_library_name_found_only_in_the_current_folder_is_pointed_at(stub_library, stub_log, monkeypatch):
    monkeypatch.chdir(stub_library.parent)         # the loader does not look here for a bare name
    with pytest.raises(LibkheperaError, match=r"\./libkhepera\.so is here: pass that"):
        KheperaIV(library_path="libkhepera.so")
    KheperaIV(library_path="./libkhepera.so").close()


def test_a_library_option_naming_a_folder_or_a_file_that_is_no_library_says_so(tmp_path, monkeypatch):
    """`--library c.yaml` (a calibration beside it) was told "./c.yaml is here: pass that", and `--library .`
    was told of the loader's own search folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "c.yaml").write_text("gain: 1\n")
    with pytest.raises(LibkheperaError, match=r"\./c\.yaml is here, but it is not a shared library"):
        KheperaIV(library_path="c.yaml")
    with pytest.raises(LibkheperaError, match=r"; \. is a folder: give the library file in it"):
        KheperaIV(library_path=".")


def test_a_library_without_a_needed_function_is_named(stub_log, tmp_path):
    library = compile_stub(tmp_path / "no-set-speed", "KH4_STUB_WITHOUT_SET_SPEED")
    with pytest.raises(LibkheperaError, match="has no function kh4_set_speed") as caught:
        KheperaIV(library_path=str(library))
    assert str(library) in str(caught.value)


def test_a_failing_call_names_the_function_and_its_code(stub_library, stub_log, monkeypatch):
    with KheperaIV(library_path=str(stub_library)) as driver:
        monkeypatch.setenv("KH4_STUB_FAIL", "kh4_proximity_ir")
        with pytest.raises(LibkheperaError, match="kh4_proximity_ir failed with code -4"):
            driver.proximity()
        monkeypatch.delenv("KH4_STUB_FAIL")


def test_a_robot_that_cannot_be_opened_is_reported_and_nothing_is_left_open(stub_library, stub_log, monkeypatch):
    monkeypatch.setenv("KH4_STUB_FAIL", "knet_open")
    with pytest.raises(LibkheperaError, match="Khepera4:dsPic"):
        KheperaIV(library_path=str(stub_library))
    monkeypatch.setenv("KH4_STUB_FAIL", "kh4_SetMode")
    with pytest.raises(LibkheperaError, match="kh4_SetMode failed"):
        KheperaIV(library_path=str(stub_library))
    assert calls(stub_log)[-1] == ("knet_close", {"dev": "ok"})


def test_a_stop_that_keeps_failing_raises_instead_of_pretending(stub_library, stub_log, monkeypatch):
    driver = KheperaIV(library_path=str(stub_library))
    monkeypatch.setenv("KH4_STUB_FAIL", "kh4_set_speed")
    with pytest.raises(LibkheperaError, match="kh4_set_speed"):
        driver.stop()
    assert len(speed_commands(stub_log)) == 3          # retried before giving up
    monkeypatch.delenv("KH4_STUB_FAIL")
    driver.close()


def test_a_sensor_read_that_errs_now_and_then_gives_the_last_good_value_then_raises(stub_library, stub_log,
                                                                                     monkeypatch):
    """One I2C glitch must not end a run; a bus that stays broken must not pass for a quiet IR ring."""
    monkeypatch.setenv("KH4_STUB_IR", hardware_ir({"front": 500}))
    with KheperaIV(library_path=str(stub_library)) as driver:
        good, odometry = driver.proximity(), driver.encoders()
        monkeypatch.setenv("KH4_STUB_FAIL", "kh4_proximity_ir")
        assert [driver.proximity() for _ in range(5)] == [good] * 5
        with pytest.raises(LibkheperaError, match="kh4_proximity_ir failed"):
            driver.proximity()                                  # the sixth in a row
        monkeypatch.setenv("KH4_STUB_FAIL", "kh4_get_position")
        assert driver.encoders() == odometry
        monkeypatch.setenv("KH4_STUB_FAIL", "kh4_battery_status")
        assert driver.battery_v() is None                       # an optional figure: never fatal
        monkeypatch.delenv("KH4_STUB_FAIL")
        assert driver.proximity() == good and driver.battery_v() is not None
        # A good read ends the row: glitches now and then, however many over a run, never add up to a failure.
        for sensor, read, last in (("kh4_proximity_ir", driver.proximity, good),
                                   ("kh4_get_position", driver.encoders, odometry)):
            assert read() == last
            for _ in range(3):
                monkeypatch.setenv("KH4_STUB_FAIL", sensor)
                assert [read() for _ in range(SENSOR_FAILURES_TOLERATED)] == [last] * SENSOR_FAILURES_TOLERATED
                monkeypatch.delenv("KH4_STUB_FAIL")
                assert read() == last


@pytest.mark.parametrize("function, read", [("kh4_proximity_ir", KheperaIV.proximity),
                                            ("kh4_get_position", KheperaIV.encoders)])
def test_a_glitch_on_a_sensors_first_read_is_read_again_not_fatal(stub_library, stub_log, monkeypatch, function,
                                                                  read):
    """With no good value yet to fall back on, the first read raised at once: one glitch in the first step ended
    the run as `driver failed`, though later reads are let off five times in a row."""
    monkeypatch.setenv("KH4_STUB_IR", hardware_ir({"front": 500}))
    monkeypatch.setenv("KH4_STUB_POSITION", "1000 2000")
    for failures, fatal in ((2, False), (SENSOR_FAILURES_TOLERATED + 1, True)):
        with KheperaIV(library_path=str(stub_library)) as driver:
            monkeypatch.setenv("KH4_STUB_FAIL", function)
            monkeypatch.setenv("KH4_STUB_FAIL_TIMES", str(failures))     # the stub counts it down
            if fatal:                                                  # a bus that stays broken still raises
                with pytest.raises(LibkheperaError, match=f"{function} failed"):
                    read(driver)
            else:
                assert read(driver) == read(driver)
            monkeypatch.delenv("KH4_STUB_FAIL")


def test_a_speed_command_that_errs_once_is_sent_again_not_fatal(stub_library, stub_log, monkeypatch):
    """Reads were let off a glitch, speed commands were not: one failed kh4_set_speed in a step ended the run."""
    with KheperaIV(library_path=str(stub_library)) as driver:
        monkeypatch.setenv("KH4_STUB_FAIL", "kh4_set_speed")
        monkeypatch.setenv("KH4_STUB_FAIL_TIMES", "2")
        driver.set_wheel_speeds(0.1, 0.1)
        monkeypatch.setenv("KH4_STUB_FAIL_TIMES", "3")
        with pytest.raises(LibkheperaError, match="kh4_set_speed failed"):
            driver.set_wheel_speeds(0.1, 0.1)                   # a bus that stays broken still raises
        monkeypatch.delenv("KH4_STUB_FAIL")
    assert speed_commands(stub_log) == [(147, 147)] * 6 + [(0, 0)]


@pytest.mark.parametrize("speed", ["0.5", True, b"1"])
def test_text_and_flags_are_not_wheel_speeds(stub_library, stub_log, speed):
    with KheperaIV(library_path=str(stub_library)) as driver:
        driver.set_wheel_speeds(0.2, 0.2)
        with pytest.raises(ValueError, match="left_m_s: must be a finite number of m/s"):
            driver.set_wheel_speeds(speed, 0.1)
        assert speed_commands(stub_log)[-1] == (0, 0)            # and the last command is cancelled


def test_close_idles_the_motors_even_when_the_stop_fails(stub_library, stub_log, monkeypatch):
    driver = KheperaIV(library_path=str(stub_library))
    monkeypatch.setenv("KH4_STUB_FAIL", "kh4_set_speed")
    with pytest.raises(LibkheperaError, match="kh4_set_speed"):
        driver.close()
    assert calls(stub_log)[-2:] == [("kh4_SetMode", {"mode": "0", "dev": "ok"}), ("knet_close", {"dev": "ok"})]


@pytest.mark.parametrize("failing, said", [
    ("kh4_SetMode", "kh4: at exit, the wheels are stopped, but the motors could not be set idle ({lib}: kh4_SetMode "
                    "failed with code -4)"),
    ("kh4_set_speed", "kh4: at exit, the wheels are stopped, by setting the motors idle only (the zero-speed command "
                      "failed: {lib}: kh4_set_speed failed with code -4)"),
    ("kh4_set_speed,kh4_SetMode", "kh4: cannot stop the wheels at exit: the zero-speed command failed ({lib}: "
                                  "kh4_set_speed failed with code -4), and so did setting the motors idle ({lib}: "
                                  "kh4_SetMode failed with code -4)"),
])
def test_closing_at_exit_says_which_of_its_calls_failed(stub_library, stub_log, monkeypatch, capsys, failing, said):
    """Zero speeds and idle motors each stop the wheels: "cannot stop the wheels at exit" was said when only the
    idling failed, after zero speeds had passed."""
    driver = KheperaIV(library_path=str(stub_library))
    driver.set_wheel_speeds(0.2, 0.2)
    monkeypatch.setenv("KH4_STUB_FAIL", failing)
    driver._stop_at_exit()                                 # what atexit runs
    assert capsys.readouterr().err == said.format(lib=stub_library) + "\n"
    assert driver.closed


# --- stopping on every way out ------------------------------------------------------------------------------
def test_close_stops_the_wheels_idles_the_motors_and_later_stops_are_harmless(stub_library, stub_log):
    driver = KheperaIV(library_path=str(stub_library))
    driver.set_wheel_speeds(0.3, 0.3)
    driver.close()
    tail = calls(stub_log)[-3:]
    assert tail == [("kh4_set_speed", {"left": "0", "right": "0", "dev": "ok"}),
                    ("kh4_SetMode", {"mode": "0", "dev": "ok"}), ("knet_close", {"dev": "ok"})]
    logged = len(calls(stub_log))
    driver.stop()
    driver.close()
    assert len(calls(stub_log)) == logged               # nothing more reaches the closed device
    with pytest.raises(LibkheperaError, match="closed"):
        driver.set_wheel_speeds(0.1, 0.1)


CHILD_SCRIPT = """\
import signal, sys
from onboard.drivers.kh4 import KheperaIV

def terminate(signum, frame):          # what the agent does: turn SIGTERM into an orderly exit
    raise SystemExit(0)

signal.signal(signal.SIGTERM, terminate)
driver = KheperaIV(library_path=sys.argv[1])
if sys.argv[2] in ("sigkill", "guarded", "idle-fails"):
    driver.start_guard()               # what the agent does with the kh4 driver
driver.set_wheel_speeds(0.2, 0.2)
if sys.argv[2] == "idle-fails":        # from now on, in this process only: its close() cannot idle the motors
    import os
    os.environ["KH4_STUB_FAIL"] = "kh4_SetMode"
print("driving", flush=True)
if sys.argv[2] == "raise":
    raise RuntimeError("a behaviour bug")
sys.stdin.read()                       # wait here until the test signals us
"""


# The robots' own Python where `make test` could build it (tests/test_robot_python.py): the driver's ctypes
# calls and its stop on exit run on 3.9 and the oldest numpy there as on this Python.
ROBOT_PYTHON = ROOT / ".venv-robot" / "bin" / "python"
INTERPRETERS = [pytest.param(sys.executable, id="this-python"),
                pytest.param(str(ROBOT_PYTHON), id="robot-python", marks=pytest.mark.skipif(
                    not ROBOT_PYTHON.exists(), reason="no .venv-robot (make robot-venv, where a Python 3.9 is)"))]


def run_child(stub_library: Path, stub_log: Path, tmp_path: Path, mode: str,
              python: str = sys.executable) -> subprocess.CompletedProcess:
    script = tmp_path / "child.py"
    script.write_text(CHILD_SCRIPT)
    env = dict(os.environ, PYTHONPATH=str(ROOT), KH4_STUB_LOG=str(stub_log))
    child = subprocess.Popen([python, str(script), str(stub_library), mode], env=env, cwd=tmp_path,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert child.stdout.readline() == "driving\n"
    if mode in ("sigterm", "guarded", "idle-fails"):
        child.send_signal(signal.SIGTERM)
    elif mode == "sigkill":
        child.send_signal(signal.SIGKILL)
    stdout, stderr = child.communicate(timeout=20)
    return subprocess.CompletedProcess(child.args, child.returncode, stdout, stderr)


@pytest.mark.parametrize("python", INTERPRETERS)
def test_a_process_killed_with_sigterm_stops_the_wheels(stub_library, stub_log, tmp_path, python):
    finished = run_child(stub_library, stub_log, tmp_path, "sigterm", python)
    assert finished.returncode == 0, finished.stderr
    assert speed_commands(stub_log) == [(295, 295), (0, 0)]
    assert calls(stub_log)[-1] == ("knet_close", {"dev": "ok"})


@pytest.mark.parametrize("python", INTERPRETERS)
def test_a_process_dying_of_an_exception_stops_the_wheels(stub_library, stub_log, tmp_path, python):
    finished = run_child(stub_library, stub_log, tmp_path, "raise", python)
    assert finished.returncode == 1 and "a behaviour bug" in finished.stderr
    assert speed_commands(stub_log) == [(295, 295), (0, 0)]



def wait_for_calls(log: Path, wanted, timeout_s: float = 20.0) -> List[Call]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        logged = calls(log)
        if wanted(logged):
            return logged
        time.sleep(0.05)
    return calls(log)


@pytest.mark.parametrize("python", INTERPRETERS)
def test_a_process_killed_with_sigkill_has_its_wheels_stopped_by_the_guard(stub_library, stub_log, tmp_path,
                                                                           python):
    """SIGKILL runs none of the process's own code: the guard, a process of its own, stops the wheels and
    idles the motors once the pipe from the dead process closes."""
    started = time.monotonic()
    finished = run_child(stub_library, stub_log, tmp_path, "sigkill", python)
    assert finished.returncode == -signal.SIGKILL
    logged = wait_for_calls(stub_log, lambda c: c and c[-1] == ("knet_close", {"dev": "ok"}))
    assert speed_commands(stub_log) == [(295, 295), (0, 0)]
    assert logged[-3:] == [("kh4_set_speed", {"left": "0", "right": "0", "dev": "ok"}),
                           ("kh4_SetMode", {"mode": "0", "dev": "ok"}), ("knet_close", {"dev": "ok"})]
    assert [name for name, _ in logged].count("kh4_init") == 2      # the guard opened the robot itself
    assert time.monotonic() - started < 20.0


@pytest.mark.parametrize("glitch", ["kh4_ConfigurePID", "kh4_SetSpeedProfile", "kh4_get_position", "kh4_init"])
def test_the_guard_stops_the_wheels_though_setting_up_the_motors_fails(stub_library, stub_log, monkeypatch, glitch):
    """The guard opened a whole driver to stop the wheels: motor set-up and an encoder read came first, and one
    failing call there left the dead agent's last speed on the wheels."""
    driver = KheperaIV(library_path=str(stub_library))
    driver.set_wheel_speeds(0.2, 0.2)
    monkeypatch.setenv("KH4_STUB_FAIL", glitch)          # the guard's environment: its calls fail there
    driver.start_guard()
    try:
        driver.guard.pipe.close()                        # the agent dies without saying it stopped the wheels
        assert driver.guard.process.wait(timeout=20) == 0
    finally:
        monkeypatch.delenv("KH4_STUB_FAIL")
        driver.guard.pipe = None
        driver.close()
    logged = calls(stub_log)
    first_guard_call = [name for name, _ in logged].index("kh4_init", 1)
    assert ("kh4_set_speed", {"left": "0", "right": "0", "dev": "ok"}) in logged[first_guard_call:]
    assert ("kh4_SetMode", {"mode": "0", "dev": "ok"}) in logged[first_guard_call:]


@pytest.mark.parametrize("failing, code, said", [
    ("kh4_SetMode", 0, "they are stopped now, but the motors could not be set idle ({lib}: kh4_SetMode failed "
                       "with code -4)"),
    ("kh4_set_speed", 0, "they are stopped now, by setting the motors idle only (the zero-speed command failed: "
                         "{lib}: kh4_set_speed failed with code -4)"),
    ("kh4_set_speed,kh4_SetMode", 1, "and they could not be stopped: the zero-speed command failed ({lib}: "
                                     "kh4_set_speed failed with code -4), and so did setting the motors idle ({lib}: "
                                     "kh4_SetMode failed with code -4)"),
    ("knet_open", 1, "and they could not be stopped: {lib}: knet_open could not open Khepera4:dsPic"),
])
def test_the_guard_says_which_of_its_calls_failed(stub_library, stub_log, monkeypatch, capsys, failing, code, said):
    """Zero speeds and idle motors each stop the wheels: the guard said "they could not be stopped" when only the
    idling failed, after zero speeds had passed."""
    monkeypatch.setenv("KH4_STUB_FAIL", failing)
    assert guard(str(stub_library), 4242, io.BytesIO(b"")) == code       # the agent died without a word
    assert capsys.readouterr().err.startswith("kh4 wheel guard: agent 4242 ended without stopping the wheels"
                                              + ("; " if code == 0 else ", ") + said.format(lib=stub_library))


def test_the_guard_says_the_agent_stopped_the_wheels_when_only_idling_the_motors_failed(stub_library, stub_log,
                                                                                         tmp_path):
    """close() stopped the wheels and failed only to idle the motors (WheelsStoppedPartly): the guard, left armed,
    tried both again, rightly, but said "agent N ended without stopping the wheels" of a robot standing still."""
    finished = run_child(stub_library, stub_log, tmp_path, "idle-fails")
    assert finished.returncode == 0, finished.stderr
    lib = stub_library
    assert f"kh4: at exit, the wheels are stopped, but the motors could not be set idle ({lib}: kh4_SetMode " \
           "failed with code -4)\n" in finished.stderr
    guard_lines = [line for line in finished.stderr.splitlines() if line.startswith("kh4 wheel guard:")]
    assert len(guard_lines) == 1 and "without stopping" not in guard_lines[0], finished.stderr
    assert guard_lines[0].endswith(f"stopped the wheels before it ended, but the motors could not be set idle "
                                   f"({lib}: kh4_SetMode failed with code -4); the guard tried both again, and "
                                   "both passed"), guard_lines[0]
    logged = wait_for_calls(stub_log, lambda c: [name for name, _ in c].count("knet_close") == 2)
    assert [name for name, _ in logged].count("kh4_init") == 2      # the guard still tried both again
    assert logged[-2:] == [("kh4_SetMode", {"mode": "0", "dev": "ok"}), ("knet_close", {"dev": "ok"})]


@pytest.mark.parametrize("failing, code, said", [
    ("", 0, "the guard tried both again, and both passed"),
    ("kh4_SetMode", 0, "the guard tried both again: the wheels are stopped, but the motors could not be set idle "
                       "({lib}: kh4_SetMode failed with code -4)"),
    ("kh4_set_speed,kh4_SetMode", 0, "the guard tried both again, and failed: the zero-speed command "
                                     "failed ({lib}: kh4_set_speed failed with code -4), and so did setting the "
                                     "motors idle ({lib}: kh4_SetMode failed with code -4)"),
])
def test_the_guard_says_what_the_agents_close_did_and_what_it_did_after(stub_library, stub_log, monkeypatch, capsys,
                                                                         failing, code, said):
    from onboard.drivers.kh4_guard import stopped_partly_note

    monkeypatch.setenv("KH4_STUB_FAIL", failing)
    note = stopped_partly_note("by setting the motors idle only (the zero-speed command failed: X)")
    assert guard(str(stub_library), 4242, io.BytesIO(note)) == code
    assert capsys.readouterr().err == (
        "kh4 wheel guard: agent 4242 stopped the wheels before it ended, by setting the motors idle only (the "
        f"zero-speed command failed: X); {said.format(lib=stub_library)}\n")


def test_the_guard_outlives_a_sigterm_to_every_process_and_stops_the_wheels_when_the_agent_dies(
        stub_library, stub_log, monkeypatch):
    """systemd stops a service with SIGTERM to each of its processes. The guard died of it at once, so an agent
    stuck in a libkhepera call (deaf to signals) and then killed left its wheels turning."""
    from onboard.drivers.kh4_guard import WheelGuard

    monkeypatch.setenv("KH4_STUB_LOG", str(stub_log))
    stub_log.touch()
    guard_process = WheelGuard.start(str(stub_library)).process
    try:
        deadline = time.monotonic() + 20.0
        while not signal_ignored(guard_process.pid, signal.SIGTERM):       # started, and ready for it
            assert guard_process.poll() is None and time.monotonic() < deadline
            time.sleep(0.05)
        guard_process.send_signal(signal.SIGTERM)
        guard_process.send_signal(signal.SIGINT)
        time.sleep(0.5)
        assert guard_process.poll() is None, "the guard died of SIGTERM"
        guard_process.stdin.close()          # the agent's end of the pipe: closed as a killed agent's is
        assert guard_process.wait(timeout=20) == 0
    finally:
        if guard_process.poll() is None:
            guard_process.kill()
    assert speed_commands(stub_log) == [(0, 0)]


def signal_ignored(pid: int, signum: int) -> bool:
    """Whether process ``pid`` ignores ``signum`` (its SigIgn mask in /proc)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    mask = next(line.split()[1] for line in status.splitlines() if line.startswith("SigIgn:"))
    return bool(int(mask, 16) >> (signum - 1) & 1)


def test_an_agent_whose_driver_call_hangs_exits_and_the_guard_stops_the_wheels(stub_library, stub_log, tmp_path):
    """A libkhepera call that never returned (a stuck bus) froze the agent: deaf to SIGTERM and SIGINT (Python
    runs signal handlers between calls), its wheels on their last speed, the hub's e-stop unheard."""
    flag = tmp_path / "hang-now"
    env = dict(os.environ, PYTHONPATH=str(ROOT), KH4_STUB_LOG=str(stub_log), KH4_STUB_HANG="kh4_battery_status",
               KH4_STUB_HANG_AFTER=str(flag))
    stub_log.touch()
    agent = subprocess.Popen([sys.executable, "-m", "onboard.agent", "--id", "0", "--driver", "kh4", "--library",
                              str(stub_library), "--hub", "tcp://127.0.0.1:9"],
                             env=env, cwd=tmp_path, stderr=subprocess.PIPE, text=True)
    try:
        assert wait_for_calls(stub_log, lambda c: ("kh4_battery_status", {"dev": "ok"}) in c)   # telemetry reads it
        flag.touch()
        assert wait_for_calls(stub_log, lambda c: ("kh4_battery_status", {"hang": "yes"}) in c)
        hung_at = time.monotonic()
        agent.send_signal(signal.SIGTERM)
        _, stderr = agent.communicate(timeout=20)
    finally:
        if agent.poll() is None:
            agent.kill()
    assert agent.returncode == 1
    assert time.monotonic() - hung_at < 10.0
    assert "agent 0: the driver's battery_v() has not returned for 2." in stderr, stderr
    logged = wait_for_calls(stub_log, lambda c: c and c[-1] == ("knet_close", {"dev": "ok"}))
    assert logged[-3:] == [("kh4_set_speed", {"left": "0", "right": "0", "dev": "ok"}),
                           ("kh4_SetMode", {"mode": "0", "dev": "ok"}), ("knet_close", {"dev": "ok"})]
    assert [name for name, _ in logged].count("kh4_init") == 2      # the guard opened the robot itself


def test_the_guard_leaves_the_wheels_alone_after_an_orderly_exit(stub_library, stub_log, tmp_path):
    finished = run_child(stub_library, stub_log, tmp_path, "guarded")
    assert finished.returncode == 0, finished.stderr
    time.sleep(1.0)                                              # time enough for a guard to act, if it did
    assert [name for name, _ in calls(stub_log)].count("kh4_init") == 1
    assert speed_commands(stub_log) == [(295, 295), (0, 0)]


def test_an_agent_given_another_robots_calibration_says_so(stub_library, stub_log, tmp_path):
    """The file's `robot:` was only kept: robot 0 ran on robot 3's IR curves (one file copied everywhere) unsaid."""
    calibration = write_yaml(tmp_path / "kh4-3.yaml", """
        robot: 3
        proximity: [{ambient: 60, touch: 980}, {ambient: 60, touch: 980}, {ambient: 60, touch: 980},
                    {ambient: 60, touch: 980}, {ambient: 60, touch: 980}, {ambient: 60, touch: 980},
                    {ambient: 60, touch: 980}, {ambient: 60, touch: 980}]
        """)
    env = dict(os.environ, PYTHONPATH=str(ROOT), KH4_STUB_LOG=str(stub_log))
    said = {}
    stub_log.touch()
    for opened, robot in enumerate(("3", "0"), start=1):
        agent = subprocess.Popen([sys.executable, "-m", "onboard.agent", "--id", robot, "--driver", "kh4", "--library",
                                  str(stub_library), "--calibration", str(calibration), "--hub", "tcp://127.0.0.1:9"],
                                 env=env, cwd=tmp_path, stderr=subprocess.PIPE, text=True)
        try:
            wait_for_calls(stub_log, lambda c, n=opened: c.count(("kh4_SetMode", {"mode": "2", "dev": "ok"})) >= n)
            time.sleep(0.5)
        finally:
            agent.send_signal(signal.SIGTERM)
            said[robot] = agent.communicate(timeout=20)[1]
    assert "measured on robot" not in said["3"], said["3"]
    assert (f"agent 0: warning: the IR calibration {calibration} was measured on robot 3, not on this robot (0): "
            "its readings follow robot 3's sensors") in said["0"], said["0"]


def test_an_agent_whose_wheels_cannot_be_stopped_says_so_in_one_line_and_exits(stub_library, stub_log, tmp_path):
    """The bus refuses every speed command: the agent's first stop (its watchdog, no hub yet) fails; it leaves
    with one line per layer that tried (agent, driver at exit, wheel guard), no traceback, and exit code 1."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), KH4_STUB_LOG=str(stub_log), KH4_STUB_FAIL="kh4_set_speed")
    done = subprocess.run([sys.executable, "-m", "onboard.agent", "--id", "0", "--driver", "kh4", "--library",
                           str(stub_library), "--hub", "tcp://127.0.0.1:9"], env=env, cwd=tmp_path,
                          capture_output=True, text=True, timeout=30)
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    assert "agent: error: the driver failed: " in done.stderr and "kh4_set_speed failed" in done.stderr
    logged = wait_for_calls(stub_log, lambda c: [name for name, _ in c].count("knet_close") == 2)
    assert ("kh4_SetMode", {"mode": "0", "dev": "ok"}) in logged      # the motors idled all the same
