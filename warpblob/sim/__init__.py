"""Soft-body simulation: implicit co-rotational linear FEM on tetrahedra, with embedded surfaces (SPEC section 5.1).

:class:`Simulation` steps a :class:`~warpblob.mesh.TetMesh` (Müller & Gross
2004): per-tet rotations by polar decomposition, backward Euler solved by a
matrix-free preconditioned conjugate gradient, fixed nodes, a frictional
ground; a surface rides on the tets by barycentric coordinates.
"""

from ._elements import Elements
from ._embed import Embedding
from ._simulation import Simulation

__all__ = ["Simulation", "Elements", "Embedding"]
