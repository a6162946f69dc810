"""Per-robot IR calibration: how each proximity sensor's raw counts become the HAL's 0..1 reading.

Every KheperaIV's IR sensors differ (emitter strength, ambient light, surface), so each robot may carry a
small YAML file, measured on the lab PC (``calibration/kh4-<id>.yaml``) and copied to the robot. The
schema is in docs/driver.md. Without a file the driver uses :func:`default_calibration`: raw / 1023,
clipped to [0, 1]. Pure stdlib + numpy + pyyaml, because robots load it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np

from onboard.config import ConfigError, check_range, from_mapping, join
from onboard.filekinds import CALIBRATION, wrong_kind
from onboard.hal import PROXIMITY_SENSOR_COUNT
from onboard.protocol_schema import MAX_ROBOT_ID
from onboard.yamlfile import read_yaml

#: Largest raw IR count: the dsPic's ADC is 10-bit (libkhepera's KH4_MAX_IR_VALUE is 1024 counts).
IR_RAW_MAX = 1023

CALIBRATION_LABEL = "calibration file"    # the field of an error about the file as a whole (missing, unreadable)


@dataclass
class SensorCalibration:
    """One sensor's raw-count to 0..1 map: either linear (``ambient``, ``touch``) or a ``points`` table."""

    ambient: Optional[float] = None   # raw count with nothing in range: reads 0
    touch: Optional[float] = None     # raw count with an obstacle touching the sensor: reads 1
    points: Optional[List[Tuple[float, float]]] = None  # [raw, value] pairs, raw increasing; linear between

    def validate(self, where: str) -> None:
        linear = self.ambient is not None or self.touch is not None
        if linear and self.points is not None:
            raise ConfigError(where, "give either ambient and touch, or points, not both")
        if linear:
            self._validate_linear(where)
        elif self.points is not None:
            self._validate_points(where)
        else:
            raise ConfigError(where, "needs ambient and touch, or points")

    def _validate_linear(self, where: str) -> None:
        for name in ("ambient", "touch"):
            if getattr(self, name) is None:
                raise ConfigError(join(where, name), "is required with a linear calibration")
            check_range(join(where, name), getattr(self, name), 0, IR_RAW_MAX)
        if self.touch <= self.ambient:
            raise ConfigError(join(where, "touch"), f"must be > ambient ({self.ambient:g}) (got {self.touch:g})")

    def _validate_points(self, where: str) -> None:
        if len(self.points) < 2:
            raise ConfigError(join(where, "points"), f"needs at least 2 [raw, value] pairs (got {len(self.points)})")
        for i, (raw, value) in enumerate(self.points):
            check_range(f"{join(join(where, 'points'), i)}[0]", raw, 0, IR_RAW_MAX)
            check_range(f"{join(join(where, 'points'), i)}[1]", value, 0.0, 1.0)
            if i and raw <= self.points[i - 1][0]:
                raise ConfigError(f"{join(join(where, 'points'), i)}[0]",
                                  f"raw counts must increase (got {raw:g} after {self.points[i - 1][0]:g})")
            if i and value < self.points[i - 1][1]:     # as touch > ambient: a larger count is a nearer obstacle
                raise ConfigError(f"{join(join(where, 'points'), i)}[1]",
                                  "readings must not decrease as raw counts increase (a larger count is a nearer "
                                  f"obstacle) (got {value:g} after {self.points[i - 1][1]:g})")

    def normalise(self, raw: float) -> float:
        """Map one raw count to [0, 1]; counts outside the calibrated range clip to its ends."""
        if self.points is not None:
            raws, values = zip(*self.points)
            return float(np.interp(raw, raws, values))   # holds the end values beyond the table
        fraction = (raw - self.ambient) / (self.touch - self.ambient)
        return min(1.0, max(0.0, fraction))


@dataclass
class IRCalibration:
    """The eight ring sensors' calibrations, in the HAL's order (0 forward, counter-clockwise)."""

    proximity: List[SensorCalibration]
    robot: Optional[int] = None   # the robot the file was measured on (informational)
    notes: str = ""               # free text: date, surface, lighting

    def validate(self, where: str) -> None:
        if len(self.proximity) != PROXIMITY_SENSOR_COUNT:
            raise ConfigError(join(where, "proximity"),
                              f"must list {PROXIMITY_SENSOR_COUNT} sensors in HAL order (got {len(self.proximity)})")
        if self.robot is not None:      # an agent's --id is 0..MAX_ROBOT_ID: no agent could match another
            check_range(join(where, "robot"), self.robot, 0, MAX_ROBOT_ID)

    def normalise(self, raw_hal_order: List[int]) -> List[float]:
        """Eight raw counts in HAL order to eight readings in [0, 1]."""
        return [sensor.normalise(raw) for sensor, raw in zip(self.proximity, raw_hal_order)]


def default_calibration() -> IRCalibration:
    """What a robot without a calibration file uses: reading = raw / 1023, clipped to [0, 1]."""
    linear = SensorCalibration(ambient=0.0, touch=float(IR_RAW_MAX))
    return IRCalibration(proximity=[linear] * PROXIMITY_SENSOR_COUNT, notes="default: raw / 1023")


def load_calibration(path: Union[str, Path]) -> IRCalibration:
    """Read and validate a calibration file; every error is a ConfigError naming the file and the field."""
    path = Path(path)
    data = read_yaml(path, CALIBRATION_LABEL)
    other = wrong_kind(data, CALIBRATION)    # a scenario or lab config given as --calibration
    if other:
        raise ConfigError(str(path), other)
    try:
        return from_mapping(IRCalibration, data)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err.field}" if err.field else str(path), err.problem) from err


__all__ = ["IR_RAW_MAX", "SensorCalibration", "IRCalibration", "default_calibration", "load_calibration"]
