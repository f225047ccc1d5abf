"""warpblob: BlobTree modelling of soft tissue on NVIDIA Warp.

Build a model from skeletal primitives and operators, then evaluate its field
with Warp kernels on the CPU or CUDA::

    import warpblob as wb
    model = wb.Point((0, 0, 0), 1.0) + wb.Segment((0, 0, 0), (1, 0, 0), 0.6)
    values = wb.field(model, [[0.2, 0.0, 0.0]])
"""

import os as _os

import warp as _wp

if not _os.environ.get("WARPBLOB_VERBOSE"):
    # keep Warp's start-up and module-load messages out of library and CLI output
    _wp.config.log_level = 30

from . import scenes  # noqa: E402
from ._errors import MeshError, ModelError, ResourceError, SceneError, SimulationError, ToolError, CutError, WarpblobError
from ._linearize import LinearModel, linearize
from ._parallel import set_thread_count, thread_count
from .field import VolumeEstimate, color, evaluate, field, gradient, monte_carlo_volume
from . import mesh
from .mesh import SurfaceMesh, TetMesh, TetQuality, TetStructure, quality
from .io._meshfile import load_mesh
from .polygonize import polygonize
from . import sim
from .sim import Simulation
from .tetrahedralize import PinchedBoundaryError, PinchedBoundaryWarning, tetrahedralize
from . import tools
from . import cut
from . import scenarios
from .slice import slice
from .tree import (
    ISO_DISTANCE,
    ISO_VALUE,
    Bend,
    Blend,
    Box,
    Cone,
    Cylinder,
    Difference,
    Disc,
    Inflate,
    Intersection,
    Node,
    Point,
    Polygon,
    Revolve,
    Ring,
    Segment,
    Sketch,
    SmoothBlend,
    Sweep,
    Taper,
    Transform,
    Triangle,
    Twist,
    Union,
)

__version__ = "0.1.0"


def __getattr__(name):
    # ``warpblob.usd`` loads pxr, so it is imported on first use only
    if name == "usd":
        import importlib

        return importlib.import_module(".usd", __name__)
    raise AttributeError(f"module 'warpblob' has no attribute {name!r}")

__all__ = [
    "WarpblobError",
    "ModelError",
    "SceneError",
    "ResourceError",
    "MeshError",
    "SimulationError",
    "ToolError",
    "CutError",
    "PinchedBoundaryError",
    "PinchedBoundaryWarning",
    "ISO_VALUE",
    "ISO_DISTANCE",
    "Node",
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
    "Sweep",
    "Revolve",
    "Blend",
    "Union",
    "Intersection",
    "Difference",
    "SmoothBlend",
    "Twist",
    "Taper",
    "Bend",
    "Transform",
    "LinearModel",
    "linearize",
    "field",
    "gradient",
    "color",
    "evaluate",
    "monte_carlo_volume",
    "VolumeEstimate",
    "polygonize",
    "tetrahedralize",
    "SurfaceMesh",
    "TetMesh",
    "TetQuality",
    "TetStructure",
    "quality",
    "mesh",
    "thread_count",
    "set_thread_count",
    "sim",
    "Simulation",
    "scenes",
    "tools",
    "scenarios",
    "slice",
    "cut",
    "load_mesh",
]
