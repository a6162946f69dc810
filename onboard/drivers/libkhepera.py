"""K-Team's libkhepera through ctypes: loading it, its functions and constants, and stopping a robot with it.

Every function is declared with the prototype of libkhepera's ``kb_khepera4.h`` / ``knet.h``, and every
constant below is libkhepera's, so the same code drives a robot's real ``libkhepera.so`` and the stand-in
that the tests compile (tests/kh4_stub/). The driver built on it is :class:`onboard.drivers.kh4.KheperaIV`;
the wheel guard (:mod:`onboard.drivers.kh4_guard`) needs only :func:`stop_robot`.
"""
from __future__ import annotations

import ctypes
import os
from typing import Any, Callable, Dict, List, Optional, Tuple

from onboard.drivers import DriverError

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

LIBRARY_ENV = "KHEPRI_LIBKHEPERA"
DEFAULT_LIBRARY = "libkhepera.so"
STOP_ATTEMPTS = 3               # a speed command or stop that fails on the I2C bus is retried before giving up

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


def _found_instead(path: str) -> str:
    """What is at ``path`` that the loader did not take: a folder (the loader named its own search path), or a
    file of that bare name in the current folder, which the loader never searches (pass ./NAME), unless it is
    no shared library at all (a calibration file given as --library was offered as the fix)."""
    if os.path.isdir(path):
        return f"; {path} is a folder: give the library file in it"
    if os.sep in path or not os.path.isfile(path):
        return ""
    try:
        with open(path, "rb") as file:
            is_library = file.read(4) == b"\x7fELF"
    except OSError:
        is_library = False
    return f"; ./{path} is here: pass that" if is_library else f"; ./{path} is here, but it is not a shared library"


class Libkhepera:
    """The loaded library: each function declared with its C prototype, each return code checked."""

    def __init__(self, path: str):
        self.path = path
        try:
            self._cdll = ctypes.CDLL(path)
        except OSError as err:
            # The default name found by no one: say where to give the path. A path given: it is that path.
            where = f"; pass --library PATH or set {LIBRARY_ENV}" if path == DEFAULT_LIBRARY else ""
            raise LibkheperaError(f"cannot load libkhepera from {path!r} ({err}){_found_instead(path)}{where}") \
                from err
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
