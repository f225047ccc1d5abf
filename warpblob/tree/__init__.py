"""The BlobTree as pure data: primitives, operators, warps and transforms.

This package never imports Warp; :func:`warpblob.linearize` turns a tree into
the flat arrays the kernels read.
"""

from ._node import ISO_VALUE, Node, Transform
from ._operators import Bend, Blend, Difference, Intersection, Operator, SmoothBlend, Taper, Twist, Union, Warp
from ._primitives import (
    ISO_DISTANCE,
    Box,
    Cone,
    Cylinder,
    Disc,
    Point,
    Polygon,
    Primitive,
    Ring,
    Segment,
    Triangle,
    falloff,
)
from ._sketch import Inflate, Revolve, Sketch, Sweep

__all__ = [
    "ISO_VALUE",
    "ISO_DISTANCE",
    "Node",
    "Transform",
    "Primitive",
    "Point",
    "Segment",
    "Disc",
    "Ring",
    "Cylinder",
    "Cone",
    "Triangle",
    "Polygon",
    "Box",
    "Sketch",
    "Inflate",
    "Revolve",
    "Sweep",
    "Operator",
    "Blend",
    "Union",
    "Intersection",
    "Difference",
    "SmoothBlend",
    "Warp",
    "Twist",
    "Taper",
    "Bend",
    "falloff",
]
