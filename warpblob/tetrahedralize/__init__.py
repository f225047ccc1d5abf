"""Tetrahedral meshing of BlobTree models by isosurface stuffing.

The method is Labelle & Shewchuk's *isosurface stuffing* (F. Labelle and
J. R. Shewchuk, "Isosurface Stuffing: Fast Tetrahedral Meshes with Good
Dihedral Angles", ACM Transactions on Graphics 26(3), SIGGRAPH 2007), the
first of the two discretizations of the source thesis (SPEC section 3). The
surface is the iso-set ``F = 0.5``; inside is ``F >= 0.5``.

Pipeline (every hot loop a Warp kernel, at most one host sync per stage to
size the next allocation):

1. **Lattice and rejection.** A body-centred cubic (BCC) lattice of spacing
   ``cellsize`` covers the model's box plus one empty cube: cube corners
   (black points) and cube centres (red points), long edges between points of
   one colour (length ``cellsize``), short edges from a centre to its cube's
   corners. Interval bounds of the field over the cubes of blocks of 8^3
   lattice cubes, then of sub-blocks of 2^3 (interval mode with its cube
   bound, see :func:`warpblob.field.bound_blocks`), prove
   regions wholly outside (skipped) or wholly inside (filled with whole lattice
   tets without a single field evaluation). On the CPU the 64 sub-blocks of a
   block that may hold surface are bounded by one bounds-rows walk of the tree
   (the polygonizer's, over the same boxes; see ``docs/field_engine.md``):
   the stage took 25 ms instead of 50 on medusa at h = 0.05, 32 instead of
   53 on towers at 0.1, with the same states (a test checks them against the
   point-by-point bounds a GPU takes).
2. **Sampling.** ``F`` at the lattice points used by a tet of a sub-block that
   may hold surface; a stand-in value on the proven side elsewhere. Labels:
   ``+`` (``F > 0.5``), ``-`` (``F < 0.5``), ``0`` (``F = 0.5``). On the CPU
   each colour's points are taken in blocks of 8^3, one array-mode tree walk
   per block that needs any (the tape pruned over the block, as the
   polygonizer samples; see ``docs/field_engine.md``); on a GPU point by
   point. The same points are sampled and the values agree up to the order
   of sums (a test checks the same tets). Sampling took 35 ms instead of
   73 ms on medusa at h = 0.05, 39 instead of 96 on towers at 0.1, 21
   instead of 55 on the head at 0.1 (2 cores, warm).
3. **Cut points.** On every lattice edge with a ``+`` and a ``-`` end, a root
   found by the bracketed Newton-Hermite search on the edge to ``|F - 0.5| <= 1e-4``,
   as the polygonizer finds its vertices: started at the root of the cubic
   through the four samples on the edge's line (lattice lines hold equally
   spaced points; the linear guess where a sample beyond the ends is a
   stand-in), each step first trying the falloff-space quadratic (exact for
   one Wyvill primitive along the edge). Root evaluations per cut point, before
   both -> after: tumor at h = 0.05 1.79 -> 1.01, medusa 0.05 2.36 -> 1.93,
   head 0.1 2.06 -> 1.99, towers 0.1 2.98 -> 2.52. Only evaluated points can
   own a crossed edge (every tet at a stand-in lies in a proven sub-block), so
   the others are not looked at: the stage took 11 ms instead of 32 on tumor,
   100 instead of 161 on medusa.
   Each edge is owned by one lattice point; per-point bit masks and a prefix
   sum give each cut point its unique index (no hashing, no duplicates).
4. **Warping.** A cut point *violates* a lattice point when it lies on one of
   the point's 14 edges closer to it than ``alpha_long`` (long edges) or
   ``alpha_short`` (short edges) times the edge length; a cut point violates at
   most one end (alpha < 1/2). A violated point moves onto a violating cut
   point and gets label ``0``; the cut points on its edges disappear (their
   edges no longer change sign). Which violated points move is settled first,
   so that **no point moves onto a cut point whose other end moves too**: in
   rounds of forced decisions (a point with a violating cut point whose other
   end stays moves; a point whose violating cut points all lead to moving
   points stays, those cut points being gone), then, for the rare cycles left,
   inside points stay and outside points move (the violation graph joins
   opposite signs, so this settles every cycle consistently). A moving point
   goes to its closest violating cut point whose other end stays (ties to the
   smaller cut index). Afterwards every surviving cut point lies in
   ``[alpha, 1 - alpha]`` of its edge and every moved point sits within alpha
   of its lattice position on an edge whose other end is an unmoved lattice
   point. The result does not depend on the thread schedule. Points that
   were not evaluated have no cut point on their edges and are not looked
   at: the stage took 12 ms instead of 31 on tumor at h = 0.05, 26 instead
   of 80 on medusa (the meshes bit for bit the same).
5. **Stencils.** Each BCC tet with at least one ``+`` vertex is replaced by
   the stencil of its sign pattern: the whole tet when no vertex is ``-``,
   else 1 to 3 tets over its ``+``/``0`` vertices and cut points (table in
   :mod:`._tables`, generated from the lattice geometry and checked by the
   tests). Quadrilateral faces are split by the paper's rules, the *parity
   rule* included, so that the two tets sharing a face always agree.
6. **Nodes.** The points and cut points used by a tet are kept and renumbered
   by a prefix sum; warped points sit on their cut point, on the surface.
7. **Materials.** Each tet gets a material id: the row of ``stats["materials"]``
   (the model's distinct primitive colours, sorted) nearest, in squared RGB
   distance with ties to the lower row, the model's colour at the tet's
   centroid (one colour evaluation per tet, :func:`warpblob.field.color`).
   Tissues are told apart by colour: the head's skull, cerebrospinal fluid,
   grey and white matter get four ids. With ``materials=[s0, s1, ...]``
   instead, the material of a tet is the innermost listed solid containing
   its centroid (the highest ``i`` with ``F_i >= 0.5``, 0 where none does),
   and the interface nodes are snapped towards the true interfaces under a
   dihedral-angle guard (:mod:`._materials`): one conforming mesh whose
   material interfaces are shared faces.
8. **Thin walls.** The boundary is checked for pinches (:mod:`._pinch`): an
   edge in more than two boundary faces, or a boundary vertex whose faces
   form more than one fan, happens where a wall or gap is thinner than the
   cells. Counts go to ``stats["pinched_edges"]`` and
   ``stats["pinched_vertices"]``; if there are any, the local thickness is
   probed along the gradient at the pinched spots and a
   :class:`PinchedBoundaryWarning` names the cell size that resolves the
   thinnest (``strict=True``: :class:`PinchedBoundaryError` instead).

``stats["seconds"]`` times each stage, from the set-up (argument checks, the
model's linearization and device copy) to building the mesh object (host
copies, statistics), so ``stats["total_seconds"]``, their sum, is the call's
time; ``stats["wall_seconds"]`` is the whole call.

Guarantees and checks. With the paper's parameter pair ``alpha_long =
0.24999``, ``alpha_short = 0.41189`` (the defaults) the paper proves, by a
computer-assisted proof, dihedral angles in **[10.7 deg, 164.8 deg]** for
every output tet (another pair gives [8.9 deg, 158.8 deg]); the proof needs
no sampling condition on the surface (the smoothness and small-cell
conditions are for the fidelity of the boundary, not for the angles). Here
the tests check: every stencil tet is positively oriented and the stencils
tile the inside part of their lattice tet; without warping, stencil dihedral
angles sampled over all admissible cut positions stay within the paper's
bounds (envelope about [12.7 deg, 155.0 deg]); the warping invariants above;
and every test mesh lies within [10.7 deg, 164.8 deg], with positive volumes,
conforming tets, a closed 2-manifold boundary whose nodes satisfy
``|F - 0.5| <= 1e-4``, and the implicit volume.

Measured: over the reference scenes (peanut, tumor, eggshell, cake,
three_slabs, mug) at 17 cell sizes from 0.06 to 0.15, the dihedral angles lie
in [12.39 deg, 152.9 deg] (smallest: three_slabs at 0.09; largest: mug). An
earlier version let a point move onto a cut point whose other end also moved
(each point took its closest violator independently); that reached 10.58 deg
on ``mug`` at cellsize 0.097 (a whole lattice tet, three of its vertices
moved, one of them toward another moved one) and 9.3 deg in the limit.

Not proven here: we have not reproduced the paper's proof. Random sampling of
the configurations the rules above allow (moved vertices at up to alpha along
any lattice edge whose other end stays, cut points in ``[alpha, 1 - alpha]``)
still reaches 9.32 deg in one stencil: lattice tet type 9 of
:func:`._tables.tet_types` (half cells ``v0 = (1,1,1)``, ``v1 = (1,1,3)`` red,
``v2 = (2,0,2)``, ``v3 = (2,2,2)`` black) with labels ``(+, 0, -, +)``,
``v1`` moved by ``alpha_short`` toward ``v3``, the cut on ``v0 v2`` at
``alpha_short`` from ``v0`` and the cut on ``v2 v3`` at ``alpha_long`` from
``v2``; stencil tet ``(v1, v0, v3, cut v2v3)``. So the paper's proof must rest
on a constraint these rules do not state (or we misread one), and the 10.7 deg
figure is the paper's claim and our measurement, not a bound proven here.

Graded interior (``interior_cellsize``). Fine cells (``cellsize``) wherever
the surface is near, coarser cubes of side ``2^L cellsize`` deep inside, for
levels ``L = 1 .. n`` with ``2^n`` the ratio ``interior_cellsize / cellsize``
rounded *down* to a power of two (a ratio below 2 gives the uniform lattice;
``interior_cellsize < cellsize`` is an error). This is a simpler, robust
alternative to the paper's octree stencils, built after warping from the
final labels, so it never touches the surface:

* a level-1 cube (2 x 2 x 2 fine cubes, aligned with the lattice) is coarse
  when every fine lattice point of it grown by one fine cube per side has
  label ``+`` (inside, unwarped); a level-``L`` cube (``L >= 2``, aligned on
  its own grid) when the eight children of it and of each of its 26
  neighbours are at level ``>= L - 1``. So no cut or warped lattice tet is
  ever replaced (every lattice tet touching the surface stays fine, with the
  uniform stencils), and the levels are 2:1 balanced across faces, edges and
  corners. Every vertex is a lattice point of the fine lattice (no new nodes).
* fine lattice tets with their cube, or the cube across the face they
  straddle, inside a coarse cube are dropped; a fine cube (or a level-``L``
  cube) sharing a face with a coarser cube fills the pyramid from its centre
  to that face with two *half-pyramids*, the square split along the diagonal
  whose ends have an even coordinate sum in units of the square (a rule of
  the square alone, so both sides agree);
* each face of a leaf cube of level ``L``: against a finer cube, the cone from
  the cube centre over the face's four half-size squares (the same diagonals:
  they all pass through the face centre); against a coarser cube, the two
  half-pyramids; against a cube of its own level with no finer cube around
  any of the face's edges, the whole BCC tets of the level's lattice across
  the face (owned by the lower cube); otherwise the cone over the fan from the
  face centre to the face's boundary, each edge that meets a finer cube split
  at its midpoint (the bisected BCC tets).

Every face shared by two tets is shared exactly (the triangulation of a face
depends only on the face and the levels of the cubes around it, which both
sides compute alike), the tets tile the same solid as the uniform mesh (the
boundary is the uniform mesh's, triangle for triangle, and the volume equal),
and the graded tets take only four shapes up to scale and symmetry, whose
dihedral angles lie in **[45 deg, 120 deg]** (cones: [45, 90]; half-pyramids:
[45, 120]; fans: [45, 90]; whole BCC tets: [60, 90]; enumerated by the
tests), so the mesh keeps the uniform mesh's bounds. One kernel per level for
the level tests and per level for the tets (count, scan, emit); the per-level
sizes and offsets are numpy bookkeeping of a few integers. Measured (2-core
CPU): tumor at 0.05 with interior 0.2: 383,394 tets uniform, 236,966 graded,
dihedral angles [17.59 deg, 144.68 deg] both (0.18 s and 0.20 s, the whole
call by wall clock, warm, best of three: the graded levels cost what the
fewer tets save); a
lone Point (radius 1, surface radius 0.4541) at 1/60 with interior 4/60:
1,033,200 tets uniform, 457,848 graded, [17.21 deg, 149.0 deg] both, nodes
182,275 against 87,141; cake at 0.05 with interior 0.4: 2.82M
uniform, 1.02M graded. Coarse cubes need room: a level-``L`` cube needs about
``2^(L+1) + 2^L`` fine cubes of all-``+`` lattice around it, so a small
model at a coarse cellsize may get no coarse cube at all (the uniform mesh).

Example:
    >>> import warpblob as wb
    >>> from warpblob.tetrahedralize import tetrahedralize
    >>> mesh = tetrahedralize(wb.scenes.peanut(), cellsize=0.1)
    >>> q = mesh.quality()
    >>> q.inverted_count, q.dihedral_min > 10.7, q.dihedral_max < 164.8
    (0, True, True)
"""

from ._materials import SNAP_MAX_DIHEDRAL, SNAP_MIN_DIHEDRAL
from ._pinch import RESOLVING_FACTOR, PinchedBoundaryError, PinchedBoundaryWarning
from ._stuffing import ALPHA_LONG, ALPHA_SHORT, tetrahedralize

__all__ = [
    "ALPHA_LONG",
    "ALPHA_SHORT",
    "PinchedBoundaryError",
    "PinchedBoundaryWarning",
    "RESOLVING_FACTOR",
    "SNAP_MAX_DIHEDRAL",
    "SNAP_MIN_DIHEDRAL",
    "tetrahedralize",
]
