"""A scenario's object and the bounds on its lengths: the shapes, their dimensions and what makes them
valid, with errors that name the field (``object.vertices: ...``). ``scenario.py`` holds the rest of a scenario.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, List, Optional, Tuple, Union

from onboard.config import ConfigError, as_written, check_range, join

from .compound import first_loose_part
from .outline import outline_fault, polygon_area

SHAPES = ("box", "circle", "polygon", "compound", "cloud", "box_rotation", "clover")
PART_SHAPES = ("box", "circle", "polygon")
IRREGULAR_SHAPES = ("cloud", "box_rotation", "clover")
DIMENSIONS = {"box": ("size",), "circle": ("size", "radius"), "polygon": ("vertices",)}   # keys each shape uses

# Every length and floor coordinate of a scenario lies within this many metres of the origin: a lab floor is
# tens of metres, the paper's largest box 12 m. The bound turns a typo (1e200, an exponent too many) into an
# error naming the field, instead of an overflow deep in the geometry or a run that only ends at its time limit.
MAX_EXTENT_M = 1000.0


def check_extent(where: str, value: float, length: bool = False) -> float:
    """A coordinate within +-MAX_EXTENT_M, or (``length``) a size in (0, MAX_EXTENT_M]."""
    if length:
        return check_range(where, value, 0.0, MAX_EXTENT_M, low_open=True)
    return check_range(where, value, -MAX_EXTENT_M, MAX_EXTENT_M)


def check_point(where: str, point: Tuple[float, float]) -> None:
    for axis, value in zip("xy", point):
        check_extent(f"{where}.{axis}", value)

# Yaws are angles, read modulo a turn; one of more than ten turns is a typo (1e308 was taken, as the remainder of
# a number whose last digit is worth far more than a turn).
MAX_YAW_DEG = 3600.0


def check_yaw(where: str, value: float) -> float:
    return check_range(where, value, -MAX_YAW_DEG, MAX_YAW_DEG)


# Masses beyond these are typos (a KheperaIV is 0.54 kg; the paper's heaviest payload 4 kg): from about 1e150 kg
# pymunk's step gives NaN poses, and a run went on with a NaN object to a NaN final error.
MAX_OBJECT_MASS_KG = 1e6


@dataclass
class ObjectPart:
    """One piece of a compound object, placed at ``offset`` (m) and ``yaw_deg`` in the object's frame."""

    shape: str = "box"
    size: Optional[Union[Tuple[float, ...], float]] = None
    radius: Optional[float] = None
    vertices: Optional[List[Tuple[float, float]]] = None
    offset: Tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0

    def validate(self, where: str) -> None:
        if self.shape not in PART_SHAPES:
            raise ConfigError(join(where, "shape"),
                              f"must be one of {', '.join(PART_SHAPES)} (got {as_written(self.shape)})")
        check_point(join(where, "offset"), self.offset)
        check_yaw(join(where, "yaw_deg"), self.yaw_deg)
        validate_dimensions(self, where)


@dataclass
class ObjectSpec:
    shape: str = "box"
    # box [w, h]; circle: radius. Any length here, so that validate_dimensions says what each shape takes
    size: Optional[Union[Tuple[float, ...], float]] = None
    radius: Optional[float] = None                              # circle
    vertices: Optional[List[Tuple[float, float]]] = None        # polygon, may be concave
    parts: Optional[List[ObjectPart]] = None                    # compound
    scale: float = 1.0                                          # multiplies the named irregular shapes
    # Foam box alone is ~0.3 kg; the paper's hardware run added 4 kg of LiPo batteries.
    mass: float = 0.3
    # Object-ground Coulomb friction coefficient. 0.3 is a middle value for foam/cardboard on a
    # smooth floor (dry-friction tables give 0.2-0.5 for such pairs). Ground friction is applied as
    # a force of friction * mass * g through a pivot joint to the static body (pymunk tank.py).
    friction: float = 0.3
    static: bool = False
    position: Tuple[float, float] = (0.0, 0.0)   # where the object's area centroid starts (m)
    yaw_deg: float = 0.0

    def validate(self, where: str) -> None:
        if self.shape not in SHAPES:
            raise ConfigError(join(where, "shape"),
                              f"must be one of {', '.join(SHAPES)} (got {as_written(self.shape)})")
        check_range(join(where, "mass"), self.mass, 0.0, MAX_OBJECT_MASS_KG, low_open=True)
        check_range(join(where, "friction"), self.friction, 0.0, 5.0)
        check_range(join(where, "scale"), self.scale, 0.0, 100.0, low_open=True)
        check_point(join(where, "position"), self.position)
        check_yaw(join(where, "yaw_deg"), self.yaw_deg)
        if self.scale != 1.0 and self.shape not in IRREGULAR_SHAPES:
            raise ConfigError(join(where, "scale"), f"only for shapes {', '.join(IRREGULAR_SHAPES)} "
                              f"(shape is {self.shape})")
        if self.shape == "compound":
            if not self.parts:
                raise ConfigError(join(where, "parts"), "a compound object needs at least one part")
        elif self.parts is not None:
            raise ConfigError(join(where, "parts"), f"only for shape: compound (shape is {self.shape})")
        validate_dimensions(self, where)
        if self.shape == "compound":
            loose = first_loose_part(self.parts)
            if loose is not None:
                part, nearest, gap = loose
                raise ConfigError(join(join(where, "parts"), part),
                                  f"does not touch the rest of the object: it lies {gap:.3g} m from part {nearest}. "
                                  "A compound object is one rigid piece; move its parts so they touch or overlap")


def validate_dimensions(spec: Any, where: str) -> None:
    """Check that a box/circle/polygon has the dimensions its shape needs, and only those."""
    shape = spec.shape
    for key in ("size", "radius", "vertices"):
        if getattr(spec, key) is not None and key not in DIMENSIONS.get(shape, ()):
            raise ConfigError(join(where, key), f"not used by shape: {shape}")
    if shape == "box":
        if not isinstance(spec.size, tuple) or len(spec.size) != 2:
            got = f" (got {list(spec.size)})" if isinstance(spec.size, tuple) else ""
            raise ConfigError(join(where, "size"), f"a box needs size: [width, height] in metres{got}")
        for i, v in enumerate(spec.size):
            check_extent(join(join(where, "size"), i), v, length=True)
    elif shape == "circle":
        if spec.radius is not None and spec.size is not None:
            raise ConfigError(join(where, "size"), "a circle takes radius or size (its radius), not both")
        radius = spec.radius if spec.radius is not None else spec.size
        if spec.radius is None and spec.size is not None and not isinstance(radius, float):
            raise ConfigError(join(where, "size"), f"a circle's size is its radius, one number in metres "
                                                   f"(got {list(spec.size)}); or give radius: <metres>")
        if not isinstance(radius, float):
            raise ConfigError(join(where, "radius"), "a circle needs radius: <metres>")
        check_extent(join(where, "radius" if spec.radius is not None else "size"), radius, length=True)
    elif shape == "polygon":
        if not spec.vertices or len(spec.vertices) < 3:
            raise ConfigError(join(where, "vertices"), "a polygon needs at least 3 vertices [[x, y], ...]")
        for i, vertex in enumerate(spec.vertices):
            check_point(join(join(where, "vertices"), i), vertex)
        fault = outline_fault(spec.vertices)
        crossing = fault is not None and fault.startswith("edges")   # a bow-tie's area is 0 too: this says why
        area = abs(polygon_area(spec.vertices))
        if area < 1e-6 and not crossing:    # a 1 mm triangle was said to be collinear
            raise ConfigError(join(where, "vertices"), "the polygon has no area (collinear or repeated points)"
                              if area < 1e-12 else f"the polygon's area is {area:.1g} m², under 1 mm x 1 mm: too "
                              "small for an object (are the vertices in metres?)")
        if crossing:
            raise ConfigError(join(where, "vertices"), f"{fault}: the outline must be a simple polygon, not meeting "
                              "itself (split such a shape into compound parts)")
        if fault is not None:       # a repeated vertex or a spike: compound parts would not mend it
            raise ConfigError(join(where, "vertices"), fault)
