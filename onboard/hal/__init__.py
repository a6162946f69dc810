"""The hardware abstraction layer: what a behaviour may sense and do, identical in simulation and on robots."""
from .devices import (
    Clock,
    DifferentialSteering,
    Odometry,
    Positioning,
    ProximitySensor,
    Radio,
    RangeAndBearingSensor,
    Robot,
    clamp_wheel_speeds,
    commanded_wheel_speeds,
)
from .records import (
    PROXIMITY_ANGLES_RAD,
    PROXIMITY_SENSOR_COUNT,
    Message,
    Neighbour,
    Neighbours,
    Pose,
    ProximityReading,
    RobotSpec,
    WheelOdometry,
    wrap_angle,
)

__all__ = [
    "Clock", "DifferentialSteering", "Odometry", "Positioning", "ProximitySensor", "Radio",
    "RangeAndBearingSensor", "Robot", "clamp_wheel_speeds", "commanded_wheel_speeds",
    "PROXIMITY_ANGLES_RAD", "PROXIMITY_SENSOR_COUNT",
    "Message", "Neighbour", "Neighbours", "Pose", "ProximityReading", "RobotSpec", "WheelOdometry", "wrap_angle",
]
