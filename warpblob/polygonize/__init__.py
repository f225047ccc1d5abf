"""Polygonization: BlobTree to watertight, coloured, shared-vertex triangle mesh.

The pipeline is the GPU design of the thesis (SPEC 2.1) on a block-sparse
grid, each stage a Warp kernel with at most one host sync:

1. Empty-space rejection by interval bounds of the field over the cubes of
   8^3-cell blocks, then of their 2^3-cell sub-blocks. Exact for BlobTree
   fields: a primitive's distance is 1-Lipschitz in its local frame (so it
   varies by at most the cube's half diagonal), a distance to a convex
   skeleton is convex (so it lies above its tangent plane at the cube's
   centre, which bounds its minimum by the half side times the 1-norm of
   its gradient), and every operator is monotone in its operands, so a cube
   whose bound excludes the iso-value holds no surface; thin plates, tiny
   blobs and a Difference's inner walls are never dropped (warps and
   sketched primitives bound as unknown).
2. Samples at the vertices next to undecided sub-blocks (array mode on the
   CPU: one tree walk per block).
3. Crossed edges and cell configurations, prefix sums (``wp.utils.array_scan``).
4. One vertex per crossed edge, on the surface to ``|F - iso| <= 1e-4``:
   a safeguarded Newton search (Press et al., *Numerical Recipes*, rtsafe)
   whose steps take the root of the quadratic in the Wyvill falloff space
   ``s = 1 - F^(1/3)`` (the squared distance over the radius for one
   primitive) through the value, the slope and the bracket's other end, else
   of the cubic Hermite interpolant through the bracket, started from the
   cubic through four samples.
5. Faces from a generated loop table, ambiguous faces resolved by the
   asymptotic decider (Nielson & Hamann, *The asymptotic decider*, IEEE
   Visualization 1991), loops fanned from the apex that maximizes the
   smallest angle; then every edge shorter than 3% of a cell is contracted
   where the link condition allows (Dey, Edelsbrunner, Guha & Nekhayev,
   *Topology preserving edge contraction*, 1999), shortest first by one
   thread of a CPU kernel over the read-back patch (union-find labels,
   Tarjan, *Efficiency of a good but not linear set union algorithm*,
   JACM 1975), which removes the needles the grid makes near its vertices
   and keeps the mesh a closed 2-manifold.
6. Tangential relaxation of the vertices of triangles under 10 degrees,
   re-projected onto the surface by Newton steps along the gradient (the
   projection of Hartmann, *A marching method for the triangulation of
   surfaces*, CAGD 1998), undone where it would turn a triangle over.

Marching cubes: Lorensen & Cline, SIGGRAPH 1987. See docs/polygonize.md.
"""

from ._pipeline import available_memory, polygonize

__all__ = ["polygonize", "available_memory"]
