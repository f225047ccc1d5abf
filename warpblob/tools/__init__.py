"""Rigid tools and their paths: the probe, scalpel and drill that push, cut and bore a model.

A :class:`Tool` is a small closed triangle mesh in its own frame; a
:class:`Pose` places it (position, then a unit quaternion in the order
(x, y, z, w)); a :class:`Path` gives its pose at any time, from keys written
in code, a straight or polyline stroke, or a time-sampled USD transform.
Every built-in tool has its working end at the local origin facing -z, so
on a path made with ``align=True`` it leads with that end. Pure numpy:
nothing here imports Warp, and ``pxr`` loads only in the USD methods.

Example:
    >>> from warpblob.tools import Drill, Path
    >>> drill = Drill(0.2, 1.0)
    >>> path = Path.line((0, 0, 1), (0, 0, 0), 2.0, align=True)  # bore straight down, bit first
    >>> drill.bounds(path.pose(2.0))[:, 2]  # the bit has reached z = 0
    array([0., 1.])
"""

from ._path import Path
from ._pose import Pose
from ._tool import Drill, Probe, Scalpel, Tool

__all__ = ["Tool", "Probe", "Scalpel", "Drill", "Pose", "Path"]
