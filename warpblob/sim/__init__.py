"""Soft-body simulation: implicit co-rotational linear FEM on tetrahedra, with embedded surfaces and tools (SPEC 5).

:class:`Simulation` steps a :class:`~warpblob.mesh.TetMesh` (Müller & Gross
2004): per-tet rotations by polar decomposition, backward Euler solved by a
matrix-free preconditioned conjugate gradient, fixed nodes, a frictional
ground; a surface rides on the tets by barycentric coordinates; rigid tools
press the tissue through the model's field carried by the deformation, a
penalty inside the implicit solve (after the contact model of Shirazian's
2014 thesis, :mod:`warpblob.sim._contact`); rigid materials move as rigid
bodies, anchored or free, coupled to the soft tissue in the same implicit
solve (:mod:`warpblob.sim._rigid`).
"""

from ._contact import ToolContact
from ._elements import Elements
from ._embed import Embedding
from ._simulation import Simulation

__all__ = ["Simulation", "Elements", "Embedding", "ToolContact"]
