"""The KheperaIV driver: wheels, IR ring, encoders and battery, over K-Team's libkhepera through ctypes
(:mod:`onboard.drivers.libkhepera`), so no C code is built for the robot. Units and the IR mapping are
documented in docs/driver.md.

Safety: :meth:`KheperaIV.stop` is idempotent and safe after :meth:`KheperaIV.close`; the driver registers
an ``atexit`` stop as a last resort, so a normal exit, ``sys.exit`` or an uncaught exception stops the
wheels. A SIGTERM/SIGINT only runs ``atexit`` if the process turns it into an exception (the agent does).
"""
from __future__ import annotations

import atexit
import ctypes
import math
import os
import sys
import threading
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Tuple, Union

from onboard.drivers import Driver, DriverError
from onboard.drivers.calibration import IRCalibration, default_calibration, load_calibration
from onboard.drivers.libkhepera import (  # noqa: F401 - also this module's names from before the split
    BATTERY_BUFFER_BYTES,
    BATTERY_V_PER_COUNT,
    DEFAULT_LIBRARY,
    DSPIC_DEVICE,
    IR_BUFFER_BYTES,
    KH4_PULSE_TO_MM,
    KH4_REG_IDLE,
    KH4_REG_SPEED_PROFILE,
    KH4_SPEED_TO_MM_S,
    KNET_BUS_I2C,
    LIBRARY_ENV,
    OPTIONAL_SIGNATURES,
    SIGNATURES,
    STOP_ATTEMPTS,
    Libkhepera,
    LibkheperaError,
    WheelsStoppedPartly,
    _retried,
    _stop_and_idle,
    open_dspic,
    resolve_library_path,
    stop_robot,
)
from onboard.hal import RobotSpec, WheelOdometry, clamp_wheel_speeds

# K-Team's tuned motor settings, as in their examples and ARGoS's real KheperaIV actuator.
MOTOR_PID = (10, 5, 1)                  # kh4_ConfigurePID(kp, ki, kd)
SPEED_PROFILE = (3, 0, 20, 1, 400)      # acc_inc, acc_div, min_speed_acc, min_speed_dec, max_speed

#: The hardware's ring order, as kh4_proximity_ir fills its buffer (registers 0x58..0x67).
HARDWARE_IR_NAMES = ("back-left", "left", "front-left", "front", "front-right", "right", "back-right", "back")
#: HAL sensor i (at i * 45 degrees, counter-clockwise from forward) reads hardware sensor HAL_TO_HARDWARE_IR[i].
HAL_TO_HARDWARE_IR = (3, 2, 1, 0, 7, 6, 5, 4)

CALIBRATION_ENV = "KHEPRI_KH4_CALIBRATION"
SENSOR_FAILURES_TOLERATED = 5   # IR or encoder reads in a row that may fail (a bus glitch) before one raises


def resolve_calibration(calibration_path: Optional[Union[str, Path]] = None) -> IRCalibration:
    """The file named by the argument, else by $KHEPRI_KH4_CALIBRATION, else the documented linear default."""
    path = calibration_path or os.environ.get(CALIBRATION_ENV)
    return load_calibration(path) if path else default_calibration()


def hardware_to_hal_order(hardware_raw: List[int]) -> List[int]:
    """Reorder the ring's raw values from libkhepera's order to the HAL's (0 forward, counter-clockwise)."""
    return [hardware_raw[hw] for hw in HAL_TO_HARDWARE_IR]


def decode_uint16_le(buffer: bytes, count: int) -> List[int]:
    return [int.from_bytes(buffer[2 * i:2 * i + 2], "little") for i in range(count)]


def wrapped_int32_delta(now: int, before: int) -> int:
    """Encoder counts are C ints that wrap at 2**31; the signed difference survives one wrap."""
    return (now - before + 2 ** 31) % 2 ** 32 - 2 ** 31


class KheperaIV(Driver):
    """Wheels, IR ring, encoders and battery of the KheperaIV this process runs on.

    ``library_path``: libkhepera.so to load (default: $KHEPRI_LIBKHEPERA, then "libkhepera.so").
    ``calibration_path``: the robot's IR calibration YAML (default: $KHEPRI_KH4_CALIBRATION, then raw/1023).
    ``max_wheel_speed_m_s``: commands beyond it are scaled down, both wheels together (keeps the turn radius).
    Open one per process: libkhepera holds the robot's I2C bus.
    """

    name = "kh4"

    def __init__(self, library_path: Optional[str] = None, calibration_path: Optional[Union[str, Path]] = None,
                 max_wheel_speed_m_s: float = RobotSpec().max_wheel_speed_m_s):
        if not (0.0 < max_wheel_speed_m_s <= RobotSpec().max_wheel_speed_m_s):
            raise ValueError(f"max_wheel_speed_m_s: must be in (0, {RobotSpec().max_wheel_speed_m_s:g}] "
                             f"(got {max_wheel_speed_m_s!r})")
        self.max_wheel_speed_m_s = max_wheel_speed_m_s
        self.calibration = resolve_calibration(calibration_path)   # bad file fails before touching hardware
        self.library = Libkhepera(resolve_library_path(library_path))
        self._lock = threading.RLock()   # re-entrant: a signal handler may stop() mid-call on the same thread
        self._dspic: Optional[int] = None
        try:
            self._open_robot()
            self._last_counts = self._read_position()   # encoders count from here
        except BaseException:
            self._release()
            raise
        self._travelled_counts = [0, 0]
        self._last_good: Dict[str, Any] = {}     # the latest reading of each sensor, for a read that errs
        self._failures: Dict[str, int] = {}      # reads in a row that erred, per sensor
        self.guard: Optional[Any] = None         # the wheel guard process, if start_guard() was called
        atexit.register(self._stop_at_exit)   # last resort; close() unregisters it

    # --- lifecycle ----------------------------------------------------------------------------------------
    def _open_robot(self) -> None:
        lib = self.library
        lib.call("kh4_init", 0, None)
        self._dspic = open_dspic(lib)
        lib.call("kh4_ConfigurePID", *MOTOR_PID, self._dspic)
        lib.call("kh4_SetSpeedProfile", *SPEED_PROFILE, self._dspic)
        lib.call("kh4_SetMode", KH4_REG_SPEED_PROFILE, self._dspic)

    @property
    def closed(self) -> bool:
        return self._dspic is None

    def close(self) -> None:
        """Stop the wheels, leave the motors idle and release the dsPic. Safe to call more than once."""
        with self._lock:
            if self.closed:
                return
            atexit.unregister(self._stop_at_exit)
            try:
                partly = _stop_and_idle(self.library, self._dspic)   # raises if neither passed
                if partly:     # the guard, not released, tries both again after us, told they stand still
                    if self.guard is not None:
                        self.guard.tell_stopped_partly(partly)
                    raise WheelsStoppedPartly(f"the wheels are stopped, {partly}")
                if self.guard is not None:
                    self.guard.release()      # stopped in order: the guard has nothing left to do
            finally:
                self._release()

    def start_guard(self) -> None:
        """Start the wheel guard (:mod:`onboard.drivers.kh4_guard`): a separate process that stops the wheels
        if this one dies without closing the driver, SIGKILL and the OOM killer included."""
        from onboard.drivers.kh4_guard import WheelGuard

        self.guard = WheelGuard.start(self.library.path)

    def _release(self) -> None:
        if self._dspic is not None:
            self.library.functions["knet_close"](self._dspic)
            self._dspic = None

    def _stop_at_exit(self) -> None:
        try:
            self.close()
        except WheelsStoppedPartly as err:     # not "cannot stop the wheels": they stand still
            print(f"kh4: at exit, {err}", file=sys.stderr)
        except DriverError as err:      # one line, not a traceback; the wheel guard tries again after us
            print(f"kh4: cannot stop the wheels at exit: {err}", file=sys.stderr)

    def __enter__(self) -> KheperaIV:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.close()

    def _require_open(self) -> int:
        if self._dspic is None:
            raise LibkheperaError(f"{self.library.path}: the KheperaIV driver is closed")
        return self._dspic

    # --- wheels -------------------------------------------------------------------------------------------
    def set_wheel_speeds(self, left_m_s: float, right_m_s: float) -> None:
        """Command wheel speeds in m/s; sends kh4_set_speed in units of KH4_SPEED_TO_MM_S (0.6781 mm/s)."""
        left_m_s = self._finite_speed("left_m_s", left_m_s)
        right_m_s = self._finite_speed("right_m_s", right_m_s)
        left_m_s, right_m_s = clamp_wheel_speeds(left_m_s, right_m_s, self.max_wheel_speed_m_s)
        left_units, right_units = self.speed_units(left_m_s), self.speed_units(right_m_s)
        # Retried as a stop is: one I2C glitch on a speed command ended the run as `driver failed`.
        _retried(STOP_ATTEMPTS, lambda: self._send_speed(left_units, right_units))

    def _finite_speed(self, name: str, value: Any) -> float:
        try:    # a number only: float("0.5") and float(True) would pass text and flags as speeds
            speed = math.nan if isinstance(value, (str, bytes, bool)) else float(value)
        except (TypeError, ValueError):
            speed = math.nan
        if not math.isfinite(speed):
            self.stop()   # never leave the previous command running after garbage
            raise ValueError(f"{name}: must be a finite number of m/s (got {value!r}); wheels stopped")
        return speed

    def speed_units(self, speed_m_s: float) -> int:
        """m/s to kh4_set_speed units, rounded, never beyond the speed limit."""
        limit = int(self.max_wheel_speed_m_s * 1000.0 / KH4_SPEED_TO_MM_S)
        units = int(round(speed_m_s * 1000.0 / KH4_SPEED_TO_MM_S))
        return max(-limit, min(limit, units))

    def _send_speed(self, left_units: int, right_units: int) -> None:
        with self._lock:
            self.library.call("kh4_set_speed", left_units, right_units, self._require_open())

    def stop(self) -> None:
        """Send 0, 0 now (retried if the bus errs). A no-op once closed: close() already stopped the wheels."""
        with self._lock:
            if self.closed:
                return
            _retried(STOP_ATTEMPTS, lambda: self._send_speed(0, 0))

    # --- sensors ------------------------------------------------------------------------------------------
    def raw_proximity(self) -> List[int]:
        """The ring's eight raw IR counts (0..1023, larger is closer) in the HAL's order."""
        buffer = ctypes.create_string_buffer(IR_BUFFER_BYTES)
        with self._lock:
            self.library.call("kh4_proximity_ir", buffer, self._require_open())
        ring = decode_uint16_le(buffer.raw, len(HARDWARE_IR_NAMES))   # the 4 ground sensors follow; unused
        return hardware_to_hal_order(ring)

    def proximity(self) -> List[float]:
        """Eight readings in [0, 1] in the HAL's order, through the robot's calibration."""
        return self._tolerated("IR", lambda: self.calibration.normalise(self.raw_proximity()))

    def _tolerated(self, sensor: str, read: Callable[[], Any]) -> Any:
        """A read that errs on the bus gives the sensor's latest good value instead, up to
        SENSOR_FAILURES_TOLERATED times in a row (one glitch must not end the run); then it raises. Before any
        good value it reads again at once, within the same count: the first step's glitch ended the run."""
        try:
            value = read()
        except LibkheperaError:
            self._failures[sensor] = self._failures.get(sensor, 0) + 1
            if self._failures[sensor] > SENSOR_FAILURES_TOLERATED:
                raise
            if sensor in self._last_good:
                return self._last_good[sensor]
            return self._tolerated(sensor, read)
        self._failures[sensor] = 0
        self._last_good[sensor] = value
        return value

    def _read_position(self) -> Tuple[int, int]:
        left, right = ctypes.c_int(0), ctypes.c_int(0)
        with self._lock:
            self.library.call("kh4_get_position", ctypes.byref(left), ctypes.byref(right), self._require_open())
        return left.value, right.value

    def encoders(self) -> WheelOdometry:
        """Signed distance each wheel rolled since the driver opened (m), from KH4_PULSE_TO_MM."""
        return self._tolerated("encoders", self._read_encoders)

    def _read_encoders(self) -> WheelOdometry:
        with self._lock:
            counts = self._read_position()
            for wheel in (0, 1):
                self._travelled_counts[wheel] += wrapped_int32_delta(counts[wheel], self._last_counts[wheel])
            self._last_counts = counts
            left, right = self._travelled_counts
        return WheelOdometry(left_m=left * KH4_PULSE_TO_MM / 1000.0, right_m=right * KH4_PULSE_TO_MM / 1000.0)

    def battery_v(self) -> Optional[float]:
        """Battery voltage from kh4_battery_status, or None if this libkhepera lacks it or the read failed (an
        optional figure for the operator: a bus error here must not stop the robot)."""
        if not self.library.has("kh4_battery_status"):
            return None
        buffer = ctypes.create_string_buffer(BATTERY_BUFFER_BYTES)
        try:
            with self._lock:
                self.library.call("kh4_battery_status", buffer, self._require_open())
        except LibkheperaError:
            return None
        return int.from_bytes(buffer.raw[10:12], "little") * BATTERY_V_PER_COUNT


__all__ = [
    "KH4_SPEED_TO_MM_S", "KH4_PULSE_TO_MM", "HARDWARE_IR_NAMES", "HAL_TO_HARDWARE_IR", "LIBRARY_ENV",
    "CALIBRATION_ENV", "DEFAULT_LIBRARY", "LibkheperaError", "WheelsStoppedPartly", "Libkhepera", "KheperaIV",
    "resolve_library_path", "resolve_calibration", "hardware_to_hal_order", "stop_robot",
]
