"""The KheperaIV IR proximity response the HAL's readings follow, and its inverse.

A reading is 1 closer than 4 cm from the sensor, 4.14 * exp(-33 d) - 0.085 from 4 to 12 cm, and 0 beyond,
clipped to [0, 1] (the curve of ARGoS's KheperaIV model). The simulator produces it; on a robot, a
calibration file's table form maps raw counts onto it (docs/driver.md), so behaviours can turn a reading
back into a distance the same way on both.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

IR_SATURATION_M = 0.04     # closer than this the reading is 1: touching and 4 cm look the same
IR_RANGE_M = 0.12          # beyond this the reading is 0
TOUCH_READING = 0.95       # at or above this a reading is taken as touching (the curve is within 2 mm of
                           # 4 cm from 0.95 up, and a touching sensor's noisy reading dips below 1)
_GAIN, _DECAY, _OFFSET = 4.14, 33.0, 0.085


def ir_response(distance: np.ndarray) -> np.ndarray:
    """Normalised reading for each distance from the sensor (m; inf = nothing seen)."""
    d = np.asarray(distance, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):
        value = _GAIN * np.exp(-_DECAY * d) - _OFFSET
    value = np.where(d < IR_SATURATION_M, 1.0, value)
    value = np.where(d > IR_RANGE_M, 0.0, value)
    return np.clip(value, 0.0, 1.0)


def ir_distance_m(reading: float) -> Optional[float]:
    """The distance (m) a reading says the obstacle is from the sensor; None for 0 (nothing in range).

    A (nearly) saturated reading is taken as touching (0 m): a robot pressing on an object reads 1, and
    the curve cannot tell it from one 4 cm away.
    """
    if reading <= 0.0:
        return None
    if reading >= TOUCH_READING:
        return 0.0
    distance = -math.log((reading + _OFFSET) / _GAIN) / _DECAY
    return min(max(distance, IR_SATURATION_M), IR_RANGE_M)
