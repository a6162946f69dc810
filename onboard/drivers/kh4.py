"""The KheperaIV driver: K-Team's libkhepera through ctypes, so no C code is built for the robot.

Every function is declared with the prototype of libkhepera's ``kb_khepera4.h`` / ``knet.h``, and every
constant below is libkhepera's, so the same class drives a robot's real ``libkhepera.so`` and the stand-in
that the tests compile (tests/kh4_stub/). Units and the IR mapping are documented in docs/driver.md.

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
from onboard.hal import RobotSpec, WheelOdometry, clamp_wheel_speeds

# --- libkhepera's constants (kb_khepera4.h, knet.h) -------------------------------------------------------
KH4_SPEED_TO_MM_S = 0.6781      # mm/s per speed unit of kh4_set_speed
KH4_PULSE_TO_MM = 0.006781      # mm per encoder pulse of kh4_get_position
KNET_BUS_I2C = 0
KH4_REG_IDLE = 0                # kh4RegIdle: motors unpowered
KH4_REG_SPEED_PROFILE = 2       # kh4RegSpeedProfile: speed control with an acceleration ramp
DSPIC_DEVICE = b"Khepera4:dsPic"
IR_BUFFER_BYTES = 24            # kh4_proximity_ir: 12 sensors x 2 bytes little-endian (8 ring, then 4 ground)
BATTERY_BUFFER_BYTES = 12       # kh4_battery_status: DS2781 registers; voltage in bytes 10-11
BATTERY_V_PER_COUNT = 0.00976   # 9.76 mV per count

# K-Team's tuned motor settings, as in their examples and ARGoS's real KheperaIV actuator.
MOTOR_PID = (10, 5, 1)                  # kh4_ConfigurePID(kp, ki, kd)
SPEED_PROFILE = (3, 0, 20, 1, 400)      # acc_inc, acc_div, min_speed_acc, min_speed_dec, max_speed

#: The hardware's ring order, as kh4_proximity_ir fills its buffer (registers 0x58..0x67).
HARDWARE_IR_NAMES = ("back-left", "left", "front-left", "front", "front-right", "right", "back-right", "back")
#: HAL sensor i (at i * 45 degrees, counter-clockwise from forward) reads hardware sensor HAL_TO_HARDWARE_IR[i].
HAL_TO_HARDWARE_IR = (3, 2, 1, 0, 7, 6, 5, 4)

LIBRARY_ENV = "KHEPRI_LIBKHEPERA"
CALIBRATION_ENV = "KHEPRI_KH4_CALIBRATION"
DEFAULT_LIBRARY = "libkhepera.so"
STOP_ATTEMPTS = 3               # a speed command or stop that fails on the I2C bus is retried before giving up
SENSOR_FAILURES_TOLERATED = 5   # IR or encoder reads in a row that may fail (a bus glitch) before one raises

_DEV = ctypes.c_void_p          # knet_dev_t *: a 64-bit pointer, never let ctypes truncate it to int
_ARGV = ctypes.POINTER(ctypes.c_char_p)
_INT_P = ctypes.POINTER(ctypes.c_int)
_CHAR = ctypes.c_char             # C char: ctypes passes small ints through

#: name -> (restype, argtypes), exactly the C prototypes.
SIGNATURES: Dict[str, Tuple[Any, List[Any]]] = {
    "kh4_init": (ctypes.c_int, [ctypes.c_int, _ARGV]),
    "knet_open": (_DEV, [ctypes.c_char_p, ctypes.c_int, ctypes.c_int, _ARGV]),
    "knet_close": (None, [_DEV]),
    "kh4_SetMode": (ctypes.c_int, [ctypes.c_int, _DEV]),
    "kh4_ConfigurePID": (ctypes.c_int, [_CHAR, _CHAR, _CHAR, _DEV]),
    "kh4_SetSpeedProfile": (ctypes.c_int, [_CHAR, _CHAR, _CHAR, _CHAR, ctypes.c_int, _DEV]),
    "kh4_set_speed": (ctypes.c_int, [ctypes.c_int, ctypes.c_int, _DEV]),
    "kh4_get_position": (ctypes.c_int, [_INT_P, _INT_P, _DEV]),
    "kh4_proximity_ir": (ctypes.c_int, [ctypes.c_char_p, _DEV]),
}
#: Functions used only if the library has them.
OPTIONAL_SIGNATURES: Dict[str, Tuple[Any, List[Any]]] = {
    "kh4_battery_status": (ctypes.c_int, [ctypes.c_char_p, _DEV]),
}


class LibkheperaError(DriverError):
    """libkhepera could not be loaded, lacks a function, or a call returned an error code."""


class WheelsStoppedPartly(LibkheperaError):
    """Closing stopped the wheels, by one of its two ways (zero speeds, idle motors); the other failed."""


def resolve_library_path(library_path: Optional[str] = None) -> str:
    """The argument, else $KHEPRI_LIBKHEPERA, else "libkhepera.so" (found by the dynamic loader)."""
    return library_path or os.environ.get(LIBRARY_ENV) or DEFAULT_LIBRARY


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


class Libkhepera:
    """The loaded library: each function declared with its C prototype, each return code checked."""

    def __init__(self, path: str):
        self.path = path
        try:
            self._cdll = ctypes.CDLL(path)
        except OSError as err:
            # A bare name is searched by the loader, never in the current folder: say so when it is there.
            here = f"; ./{path} is here: pass that" if os.sep not in path and os.path.isfile(path) else ""
            raise LibkheperaError(f"cannot load libkhepera from {path!r} ({err}){here}; pass --library PATH "
                                  f"or set {LIBRARY_ENV}") from err
        self.functions = {name: self._bind(name, *signature) for name, signature in SIGNATURES.items()}
        for name, signature in OPTIONAL_SIGNATURES.items():
            if hasattr(self._cdll, name):
                self.functions[name] = self._bind(name, *signature)

    def _bind(self, name: str, restype: Any, argtypes: List[Any]) -> Any:
        try:
            function = getattr(self._cdll, name)
        except AttributeError as err:
            raise LibkheperaError(f"{self.path}: has no function {name}; is it K-Team's libkhepera?") from err
        function.restype = restype
        function.argtypes = argtypes
        return function

    def has(self, name: str) -> bool:
        return name in self.functions

    def call(self, name: str, *args: Any) -> int:
        """Call ``name``; a negative return code raises LibkheperaError naming the function and library."""
        rc = self.functions[name](*args)
        if rc < 0:
            raise LibkheperaError(f"{self.path}: {name} failed with code {rc}")
        return rc


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


def stop_robot(library_path: str) -> Optional[str]:
    """Open the dsPic only to stop it: zero speeds (retried), then the motors idle and the dsPic closed, each tried
    whatever the one before did. The wheel guard's way in: opening a :class:`KheperaIV` configures the motors
    and reads the encoders first, so one bus error there (a glitch the driver tolerates elsewhere) left a dead
    agent's last speed on the wheels.

    None when both passed; what failed when the wheels stopped all the same (see :func:`_stop_and_idle`).
    LibkheperaError when they may still turn: the dsPic would not open, or neither call passed."""
    lib = Libkhepera(library_path)
    try:
        lib.call("kh4_init", 0, None)
    except LibkheperaError:
        pass            # knet_open says whether the robot can be reached; try it all the same
    dspic = open_dspic(lib)
    try:
        return _stop_and_idle(lib, dspic)
    finally:
        lib.functions["knet_close"](dspic)


def _stop_and_idle(lib: Libkhepera, dspic: Any) -> Optional[str]:
    """Zero speeds, then the motors idle, the second tried whatever the first did: either stops the wheels
    (unpowered motors stop them too). Said apart, since "could not be stopped" of a robot whose zero speeds
    passed, and only its idling failed, sent someone to a robot that was standing still."""
    speed = _failure(lambda: _retried(STOP_ATTEMPTS, lambda: lib.call("kh4_set_speed", 0, 0, dspic)))
    idle = _failure(lambda: _retried(STOP_ATTEMPTS, lambda: lib.call("kh4_SetMode", KH4_REG_IDLE, dspic)))
    if speed and idle:
        raise LibkheperaError(f"the zero-speed command failed ({speed}), and so did setting the motors idle ({idle})")
    if speed:
        return f"by setting the motors idle only (the zero-speed command failed: {speed})"
    if idle:
        return f"but the motors could not be set idle ({idle})"
    return None


def _failure(call: Callable[[], Any]) -> Optional[str]:
    """What ``call()`` raised as LibkheperaError, or None if it passed."""
    try:
        call()
    except LibkheperaError as err:
        return str(err)
    return None


def open_dspic(lib: Libkhepera) -> Any:
    """The dsPic's knet handle (after kh4_init), or LibkheperaError saying why it may not open."""
    dspic = lib.functions["knet_open"](DSPIC_DEVICE, KNET_BUS_I2C, 0, None)
    if not dspic:
        raise LibkheperaError(f"{lib.path}: knet_open could not open {DSPIC_DEVICE.decode()} "
                              "(is this a KheperaIV, and is no other program using it?)")
    return dspic


def _retried(attempts: int, call: Callable[[], Any]) -> None:
    """``call()`` until it does not raise LibkheperaError, at most ``attempts`` times; the last error goes on."""
    for attempt in range(1, attempts + 1):
        try:
            call()
            return
        except LibkheperaError:
            if attempt == attempts:
                raise


__all__ = [
    "KH4_SPEED_TO_MM_S", "KH4_PULSE_TO_MM", "HARDWARE_IR_NAMES", "HAL_TO_HARDWARE_IR", "LIBRARY_ENV",
    "CALIBRATION_ENV", "DEFAULT_LIBRARY", "LibkheperaError", "WheelsStoppedPartly", "Libkhepera", "KheperaIV",
    "resolve_library_path", "resolve_calibration", "hardware_to_hal_order", "stop_robot",
]
