"""Reference models: the test scenes of Shirazian's 2014 thesis, rebuilt in warpblob.

The models follow the reference models of P. Shirazian's 2014 PhD thesis on
parallel BlobTree modelling and soft-tissue simulation (University of
Victoria): the two-point *peanut*, the ten-point *tumor*, the hollow
*eggshell*, the three-tier *cake*, the *3slabs* used by the FEM experiments
(``three_slabs`` here), a *mug* built by CSG, the *towers* stress test (7,296
primitives, 7,360 operators, depth 64), *medusa* (2,920 primitives under only
11 operators, depth 6) and a layered *head* (skull, CSF, grey and white
matter). Shapes are approximations; the tree statistics of ``towers`` and
``medusa`` match the thesis exactly.

All models are in model units around the origin with z up and fit in about
``[-3, 3]^3`` (``towers`` spans about ``[-4, 4]^2 x [0, 7.3]``). Every
function builds a fresh tree on each call (trees are immutable and
:func:`warpblob.linearize` caches on the model object), so callers may keep,
transform or combine the results freely. Coordinates are written as literals
or computed deterministically: nothing is random.

Example:
    >>> import warpblob as wb
    >>> m = wb.scenes.tumor()
    >>> m.primitive_count(), m.operator_count(), m.depth()
    (10, 1, 2)
    >>> sorted(wb.scenes.ALL)[:3]
    ['cake', 'eggshell', 'head']
"""

from __future__ import annotations

import numpy as np

from ..tree import (
    ISO_DISTANCE,
    Blend,
    Box,
    Cylinder,
    Difference,
    Disc,
    Point,
    Ring,
    Segment,
    SmoothBlend,
    Union,
)

__all__ = [
    "peanut",
    "tumor",
    "eggshell",
    "cake",
    "three_slabs",
    "mug",
    "towers",
    "medusa",
    "head",
    "head_materials",
    "HEAD_TISSUES",
    "HEAD_MATERIALS",
    "default",
    "ALL",
]


# ---------------------------------------------------------------------------
# small models
# ---------------------------------------------------------------------------


def peanut():
    """Two blended point primitives: a peanut-shaped blob along x.

    Counts: 2 primitives, 1 operator (Blend), depth 2.

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.peanut()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (2, 1, 2)
    """
    shell = (0.86, 0.66, 0.42)
    return Blend(
        Point((-0.45, 0.0, 0.0), 1.0, color=shell),
        Point((0.45, 0.0, 0.0), 1.0, color=shell),
    )


#: (x, y, z, radius) of the tumor's ten lobes (fixed literals, not random)
_TUMOR_LOBES = (
    (0.00, 0.00, 0.00, 1.30),
    (0.62, 0.18, 0.10, 0.95),
    (-0.55, 0.35, -0.12, 1.00),
    (0.12, -0.66, 0.25, 0.90),
    (-0.20, 0.10, 0.70, 0.85),
    (0.35, 0.45, -0.58, 0.80),
    (-0.70, -0.42, 0.30, 0.75),
    (0.85, -0.35, -0.30, 0.70),
    (-0.15, 0.80, 0.45, 0.72),
    (0.05, -0.25, -0.82, 0.78),
)


def tumor():
    """An irregular lumpy blob: ten point primitives under one blend.

    Counts: 10 primitives, 1 operator (Blend), depth 2.

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.tumor()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (10, 1, 2)
    """
    tones = ((0.78, 0.36, 0.38), (0.70, 0.30, 0.36), (0.84, 0.46, 0.44))
    return Blend(
        [Point((x, y, z), r, color=tones[i % 3]) for i, (x, y, z, r) in enumerate(_TUMOR_LOBES)]
    )


def eggshell():
    """A thin spherical shell: a point blob minus a smaller concentric one.

    The outer surface has radius 1.362, the inner 1.181 (shell 0.18 thick).

    Counts: 2 primitives, 1 operator (Difference), depth 2.

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.eggshell()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (2, 1, 2)
        >>> float(wb.field(m, [[0.0, 0.0, 0.0]])[0]) < 0.5  # hollow inside
        True
    """
    return Difference(
        Point((0.0, 0.0, 0.0), 3.0, color=(0.96, 0.93, 0.84)),
        Point((0.0, 0.0, 0.0), 2.6, color=(0.90, 0.80, 0.55)),
    )


def cake():
    """A three-tier cake on ``z >= 0``: cylinders of decreasing size, each with an icing ring.

    The six primitives are blended, so the tiers and icing merge with smooth
    fillets. The whole box (not only the surface) lies in ``z >= 0``.

    Counts: 6 primitives, 1 operator (Blend), depth 2.

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.cake()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (6, 1, 2)
        >>> bool(m.bounds()[0][2] >= 0.0)
        True
    """
    sponge = (0.87, 0.70, 0.45)
    icing = (0.98, 0.86, 0.90)
    # (cylinder radius, bottom z, top z) of each tier; support radius 0.5
    tiers = ((2.1, 0.55, 1.15), (1.45, 1.45, 2.0), (0.8, 2.3, 2.8))
    parts = [Cylinder((0, 0, z0), (0, 0, z1), r, 0.5, color=sponge) for r, z0, z1 in tiers]
    parts += [Ring((0, 0, z1 + 0.05), (0, 0, 1), r - 0.05, 0.4, color=icing) for r, _, z1 in tiers]
    return Blend(parts)


def three_slabs():
    """Three box slabs side by side along x (the thesis' "3slabs" FEM scene).

    The green slab (lowest x) is the one the FEM tests fix to a wall; the
    others are red and blue. The slabs are unioned, so they touch (their
    surfaces overlap by about 0.06) but keep distinct colours.

    Counts: 3 primitives, 1 operator (Union), depth 2.

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.three_slabs()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (3, 1, 2)
        >>> [round(float(c), 2) for c in wb.color(m, [[-1.2, 0.0, 0.0]])[0]]  # the fixed slab is green
        [0.2, 0.75, 0.3]
    """
    half = (0.45, 1.0, 0.2)
    return Union(
        Box((-1.2, 0.0, 0.0), half, 0.4, color=(0.2, 0.75, 0.3)),
        Box((0.0, 0.0, 0.0), half, 0.4, color=(0.85, 0.3, 0.25)),
        Box((1.2, 0.0, 0.0), half, 0.4, color=(0.25, 0.4, 0.85)),
    )


def mug():
    """A coffee mug by CSG: (body cylinder | ring handle) minus a raised inner cylinder.

    The cavity cylinder starts higher than the body, so the bottom stays
    closed (0.5 thick) and the top is open. The handle is a ring in the xy
    plane rotated to stand vertical at the +x side; it is unioned with the
    body *before* the cavity is cut, so no part of it pokes into the cup.

    Counts: 3 primitives, 3 operators (Difference, Union, one Transform), depth 3.

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.mug()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (3, 3, 3)
        >>> float(wb.field(m, [[0.0, 0.0, 1.5]])[0]) < 0.5  # hollow
        True
    """
    ceramic = (0.93, 0.91, 0.86)
    body = Cylinder((0, 0, 0.4), (0, 0, 2.4), 1.0, 0.6, color=ceramic)
    handle = Ring((0, 0, 0), (0, 0, 1), 0.62, 0.36, color=(0.75, 0.22, 0.2))
    handle = handle.rotate((1, 0, 0), np.pi / 2).translate((1.72, 0.0, 1.4))
    hollow = Cylinder((0, 0, 0.9), (0, 0, 3.4), 0.76, 0.6, color=(0.86, 0.84, 0.79))
    return Difference(Union(body, handle), hollow)


# ---------------------------------------------------------------------------
# towers: 7,296 primitives, 7,360 operators, depth 64
# ---------------------------------------------------------------------------

_TOWER_GRID = 8
_TOWER_FLOORS = 57
_FLOOR_HEIGHT = 0.12
_TOWER_SPACING = 1.0


def _tower(color):
    """One tower: Union(floor_1, Union(floor_2, ... Union(floor_56, floor_57))).

    Each floor blends a thin square plate (Box) with a short core column
    (Cylinder) that reaches into the floor above, so the floors stack into one
    connected tower. 114 primitives, 113 operators, depth 58.
    """
    floors = []
    for i in range(_TOWER_FLOORS):
        z = 0.2 + _FLOOR_HEIGHT * i
        shrink = 1.0 - 0.25 * i / (_TOWER_FLOORS - 1)  # slightly tapered tower
        plate = Box((0.0, 0.0, z), (0.3 * shrink, 0.3 * shrink, 0.0), 0.1, color=color)
        core = Cylinder((0.0, 0.0, z), (0.0, 0.0, z + _FLOOR_HEIGHT), 0.15, 0.15, color=(0.55, 0.55, 0.6))
        floors.append(Blend(plate, core))
    tower = floors[-1]
    for floor in reversed(floors[:-1]):
        tower = Union(floor, tower)
    return tower


def towers():
    """An 8 x 8 grid of 57-floor towers: the thesis' large stress-test model.

    Each tower is a chain of 56 unions over 57 floors (a floor blends a Box
    plate and a Cylinder core) placed by one ``translate``; the 64 towers are
    combined by a balanced binary tree of unions, and the whole grid is
    centred by one root ``translate``. Spans about ``[-3.9, 3.9]^2 x [0.1, 7.2]``.

    Counts: 7,296 primitives (64 x 114), 7,360 operators (64 x 113 operators,
    64 tower transforms, 63 grid unions, 1 root transform), depth 64
    (6 grid levels + 56 chain unions + floor blend + primitive).

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.towers()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (7296, 7360, 64)
    """
    palette = ((0.72, 0.74, 0.80), (0.80, 0.72, 0.60), (0.62, 0.70, 0.78), (0.78, 0.66, 0.66))
    level = []
    for j in range(_TOWER_GRID):
        for i in range(_TOWER_GRID):
            t = _tower(palette[(i + 2 * j) % len(palette)])
            level.append(t.translate((i * _TOWER_SPACING, j * _TOWER_SPACING, 0.0)))
    while len(level) > 1:  # balanced binary tree of unions (64 -> 1 in 6 levels)
        level = [Union(level[k], level[k + 1]) for k in range(0, len(level), 2)]
    c = 0.5 * (_TOWER_GRID - 1) * _TOWER_SPACING
    return level[0].translate((-c, -c, 0.0))


# ---------------------------------------------------------------------------
# medusa: 2,920 primitives, 11 operators, depth 6
# ---------------------------------------------------------------------------

_SKIN = (0.62, 0.72, 0.56)
_HEAD_CENTER = np.array([0.0, 0.15, 0.95])
_SNAKES_PER_BLEND = 8
_SNAKE_POINTS = 120


def _face():
    """The 38 face primitives (face looks towards -y), one blend."""
    s = _SKIN
    lips = (0.55, 0.38, 0.40)
    parts = [
        Point((0.0, 0.10, 0.95), 2.0, color=s),  # cranium
        Point((0.0, 0.45, 0.85), 1.5, color=s),  # back of the head
        Point((0.0, 0.65, 0.65), 0.8, color=s),  # occiput
        Point((-0.45, 0.05, 1.10), 1.1, color=s),  # temples
        Point((0.45, 0.05, 1.10), 1.1, color=s),
        Point((-0.30, 0.35, 1.45), 0.8, color=s),  # crown
        Point((0.30, 0.35, 1.45), 0.8, color=s),
        Point((0.0, -0.50, 1.30), 0.9, color=s),  # forehead
        Point((0.0, -0.78, 1.10), 0.35, color=s),  # brow centre
        Segment((-0.15, -0.80, 1.12), (-0.60, -0.68, 1.10), 0.30, color=s),  # brows
        Segment((0.15, -0.80, 1.12), (0.60, -0.68, 1.10), 0.30, color=s),
        Segment((0.0, -0.76, 1.02), (0.0, -0.86, 0.82), 0.30, color=s),  # nose bridge
        Segment((0.0, -0.86, 0.82), (0.0, -1.00, 0.62), 0.34, color=s),  # nose
        Point((-0.09, -0.94, 0.60), 0.22, color=s),  # nostrils
        Point((0.09, -0.94, 0.60), 0.22, color=s),
        Point((-0.50, -0.55, 0.80), 0.60, color=s),  # cheekbones
        Point((0.50, -0.55, 0.80), 0.60, color=s),
        Point((-0.42, -0.55, 0.55), 0.85, color=s),  # cheeks
        Point((0.42, -0.55, 0.55), 0.85, color=s),
        Point((0.0, -0.25, 0.40), 1.30, color=s),  # jaw
        Point((-0.55, -0.10, 0.38), 0.60, color=s),  # jaw angles
        Point((0.55, -0.10, 0.38), 0.60, color=s),
        Point((0.0, -0.60, 0.18), 0.70, color=s),  # chin
        Point((0.0, -0.90, 0.48), 0.20, color=s),  # philtrum
        Segment((-0.20, -0.86, 0.40), (0.20, -0.86, 0.40), 0.24, color=lips),  # upper lip
        Segment((-0.16, -0.83, 0.31), (0.16, -0.83, 0.31), 0.24, color=lips),  # lower lip
        Point((-0.24, -0.80, 0.36), 0.22, color=lips),  # mouth corners
        Point((0.24, -0.80, 0.36), 0.22, color=lips),
        Disc((-0.98, 0.10, 0.85), (1, 0, 0), 0.14, 0.30, color=s),  # ears
        Disc((0.98, 0.10, 0.85), (1, 0, 0), 0.14, 0.30, color=s),
        Point((-1.00, 0.08, 0.62), 0.24, color=s),  # ear lobes
        Point((1.00, 0.08, 0.62), 0.24, color=s),
        Point((0.0, 0.35, 0.20), 0.80, color=s),  # nape
        Cylinder((0.0, 0.10, -0.70), (0.0, 0.05, 0.30), 0.35, 0.60, color=s),  # neck
        Segment((-0.30, -0.25, -0.65), (-0.45, 0.05, 0.35), 0.35, color=s),  # neck muscles
        Segment((0.30, -0.25, -0.65), (0.45, 0.05, 0.35), 0.35, color=s),
        Point((0.0, -0.32, -0.15), 0.45, color=s),  # throat
        Disc((0.0, 0.10, -0.85), (0, 0, 1), 0.55, 0.50, color=s),  # bust base
    ]
    return parts


def _snake_path(index):
    """(n, 3) centres and (n,) radii of snake ``index`` in 0..23 (deterministic)."""
    # roots spread over the scalp: three rings of elevation, avoiding the face
    ring, k = divmod(index, 8)
    elevation = np.radians((72.0, 42.0, 12.0)[ring])
    # azimuth 90 deg is the back (+y); the lower the ring, the wider the gap left for the face
    azimuth = np.radians(90.0 + (k - 3.5) * (40.0, 37.0, 33.0)[ring] + 6.0 * (ring == 1))
    d = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    e1 = np.cross(d, (0.0, 0.0, 1.0))
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.array([1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    t = np.linspace(0.0, 1.0, _SNAKE_POINTS)
    reach = 0.90 + 1.45 * t
    droop = 1.9 * t**2 * (0.6 + 0.4 * np.cos(elevation))
    centre = _HEAD_CENTER + np.outer(reach, d) - np.outer(droop, (0.0, 0.0, 1.0))
    turns = 3.0 + (index % 3) * 0.5
    phase = 0.7 * index
    amp = 0.16 * np.sin(np.pi * np.minimum(t * 1.4, 1.0)) + 0.02
    ang = 2.0 * np.pi * turns * t + phase
    centre += np.outer(amp * np.cos(ang), e1) + np.outer(amp * np.sin(ang), e2)
    radii = 0.20 - 0.12 * t
    return centre, radii


def _snake_blend(first):
    """One snake blend: 8 helical snakes of 120 overlapping points (960 primitives)."""
    greens = ((0.25, 0.50, 0.22), (0.38, 0.55, 0.20), (0.20, 0.42, 0.30), (0.45, 0.50, 0.25))
    prims = []
    for s in range(first, first + _SNAKES_PER_BLEND):
        centres, radii = _snake_path(s)
        col = greens[s % len(greens)]
        prims.extend(Point(c, r, color=col) for c, r in zip(centres.tolist(), radii.tolist()))
    return Blend(prims)


def medusa():
    """A head with snake hair: 2,920 primitives under only 11 operators.

    Tree: ``Union(Difference(face, eyes), hair)`` with ``face`` a blend of 38
    primitives, ``eyes`` a union of two carving points, and ``hair`` =
    ``Blend(Union(SmoothBlend(snakes_a, snakes_b)), Union(snakes_c))``; each
    snake blend holds 8 helical snakes of 120 tapering points (960
    primitives). Wide blends like these are what the linearizer's operand
    grids are for. No transform nodes.

    Counts: 2,920 primitives, 11 operators, depth 6
    (hair -> group -> smooth blend -> snake blend -> point, under the root).

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.medusa()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (2920, 11, 6)
    """
    eye_color = (0.80, 0.12, 0.10)
    face = Blend(_face())
    eyes = Union(
        Point((-0.32, -0.88, 0.88), 0.40, color=eye_color),
        Point((0.32, -0.88, 0.88), 0.40, color=eye_color),
    )
    n = _SNAKES_PER_BLEND
    hair = Blend(
        Union(SmoothBlend(_snake_blend(0), _snake_blend(n), k=2.0)),
        Union(_snake_blend(2 * n)),
    )
    return Union(Difference(face, eyes), hair)


# ---------------------------------------------------------------------------
# head: layered skull / CSF / grey matter / white matter
# ---------------------------------------------------------------------------

#: (x, y, z, radius) of the brain-shaped lobes at scale 1 (face towards -y)
_HEAD_LOBES = (
    (-0.42, -0.55, 0.25, 1.75),  # frontal
    (0.42, -0.55, 0.25, 1.75),
    (-0.45, 0.15, 0.45, 1.85),  # parietal
    (0.45, 0.15, 0.45, 1.85),
    (-0.40, 0.75, 0.05, 1.65),  # occipital
    (0.40, 0.75, 0.05, 1.65),
)
#: overall size factor of the head (its skull spans about 4 units front to back)
_HEAD_SIZE = 1.35


def _lobes(scale, color):
    """The brain-shaped blend scaled about the origin by ``scale`` (no transform node).

    Scaling a point primitive's centre and radius by ``s`` scales its field,
    so the shapes of different scales are nested copies of each other.
    """
    s = _HEAD_SIZE * scale
    return Blend([Point((s * x, s * y, s * z), s * r, color=color) for x, y, z, r in _HEAD_LOBES])


#: tissue name -> RGB colour of the :func:`head` layers, outermost first
HEAD_TISSUES = {
    "skull": (0.95, 0.93, 0.86),
    "cerebrospinal fluid": (0.62, 0.80, 0.98),
    "grey matter": (0.74, 0.62, 0.64),
    "white matter": (0.98, 0.95, 0.82),
}
#: support radius of the cut-away box: its rounded edges have radius ISO_DISTANCE times this
_CUT_RADIUS = 0.2


def head(*, cut_away: bool = False):
    """A layered head: skull, CSF, grey matter and white matter shells, unioned.

    Every layer is a difference of two scaled copies of one brain-shaped blend
    of six points, so the layers nest with small gaps (about 0.04 across,
    0.023 at the thinnest, under the head): skull (bone white), cerebrospinal
    fluid (light blue), grey matter (pinkish grey) and white matter (cream),
    the last hollowed by two ventricles (:data:`HEAD_TISSUES`). Polygonize it
    with a cell size below the thinnest gap (0.02), or neighbouring layers
    merge through it.

    Args:
        cut_away: remove the octant ``x > 0, y < 0, z > 0`` (front right top;
            the face looks towards -y) from every layer, each with a box of the
            layer's own colour so that the cut faces show the tissue; it opens
            the right ventricle too.

    Counts: 44 primitives, 13 operators (Union, 4 Differences, 7 lobe blends,
    the ventricle blend), depth 4; cut away: 48 primitives, 17 operators
    (4 more Differences), depth 5.

    Example:
        >>> import warpblob as wb
        >>> m = wb.scenes.head()
        >>> m.primitive_count(), m.operator_count(), m.depth()
        (44, 13, 4)
        >>> float(wb.field(wb.scenes.head(cut_away=True), [[0.1, -1.5, 0.1]])[0]) < 0.5  # inside the cut
        True
    """
    bone, csf, grey, white = HEAD_TISSUES.values()
    skull = Difference(_lobes(1.0, bone), _lobes(0.915, bone))
    fluid = Difference(_lobes(0.895, csf), _lobes(0.85, csf))
    cortex = Difference(_lobes(0.83, grey), _lobes(0.72, grey))
    h = _HEAD_SIZE
    ventricles = Blend(
        Point((-0.22 * h, 0.05 * h, 0.35 * h), 0.55 * h, color=csf),
        Point((0.22 * h, 0.05 * h, 0.35 * h), 0.55 * h, color=csf),
    )
    matter = Difference(_lobes(0.70, white), ventricles)
    layers = (skull, fluid, cortex, matter)
    if cut_away:
        # the box's surface lies ISO_DISTANCE * radius outside its skeleton: start the skeleton
        # that far inside the octant so the cut faces lie on the coordinate planes
        near, far = ISO_DISTANCE * _CUT_RADIUS, 2.0 * h * 1.85  # far: beyond every lobe's support
        c, half = 0.5 * (far + near), 0.5 * (far - near)
        layers = tuple(
            Difference(layer, Box((c, -c, c), (half, half, half), _CUT_RADIUS, color=color))
            for layer, color in zip(layers, HEAD_TISSUES.values())
        )
    return Union(*layers)


#: material names of :func:`head_materials`, in material id order (outermost first); the
#: ventricles hold cerebrospinal fluid too (ids 1 and 4 are both CSF)
HEAD_MATERIALS = ("skull", "cerebrospinal fluid", "grey matter", "white matter", "ventricles")
#: lobe scales of the contiguous head's layer surfaces: the outer skull, then the middle of each
#: gap of :func:`head` (0.915 / 0.895, 0.85 / 0.83, 0.72 / 0.70)
_HEAD_LAYER_SCALES = (1.0, 0.905, 0.84, 0.71)


def head_materials():
    """The contiguous layered head as nested solids, for ``tetrahedralize(..., materials=...)``.

    The same brain-shaped blend as :func:`head` at four scales, each solid a
    whole (filled) copy: ``skull`` (scale 1, the outer skull surface),
    ``cerebrospinal fluid`` (0.905), ``grey matter`` (0.84), ``white matter``
    (0.71), and the two ``ventricles`` inside the white matter. The material
    of a point is the innermost solid containing it, so the tissues touch:
    the skull is the shell between scales 1 and 0.905, the CSF between 0.905
    and 0.84, the grey matter between 0.84 and 0.71, and the white matter
    fills the rest but for the ventricles, which hold CSF (their own id, 4).
    Each interface lies in the middle of the corresponding gap of
    :func:`head`, so every layer keeps its thickness there plus half of each
    neighbouring gap (about 0.02 model units more).

    Returns:
        dict name -> solid in material id order (:data:`HEAD_MATERIALS`);
        ``["skull"]`` is the whole head, the domain to mesh.

    Example:
        >>> import warpblob as wb
        >>> layers = wb.scenes.head_materials()
        >>> list(layers) == list(wb.scenes.HEAD_MATERIALS)
        True
        >>> mesh = wb.tetrahedralize(layers["skull"], cellsize=0.4, materials=layers)
        >>> mesh.stats["materials"][0], sorted(set(mesh.material.tolist()))
        ('skull', [0, 1, 2, 3, 4])
    """
    colors = tuple(HEAD_TISSUES.values())
    solids = [_lobes(scale, color) for scale, color in zip(_HEAD_LAYER_SCALES, colors)]
    h = _HEAD_SIZE
    ventricles = Blend(
        Point((-0.22 * h, 0.05 * h, 0.35 * h), 0.55 * h, color=colors[1]),
        Point((0.22 * h, 0.05 * h, 0.35 * h), 0.55 * h, color=colors[1]),
    )
    return dict(zip(HEAD_MATERIALS, solids + [ventricles]))


def default():
    """The default scene: :func:`tumor`.

    Counts: 10 primitives, 1 operator, depth 2.

    Example:
        >>> import warpblob as wb
        >>> wb.scenes.default().primitive_count()
        10
    """
    return tumor()


#: name -> model function, in the thesis' order
ALL = {
    "peanut": peanut,
    "tumor": tumor,
    "eggshell": eggshell,
    "cake": cake,
    "three_slabs": three_slabs,
    "mug": mug,
    "towers": towers,
    "medusa": medusa,
    "head": head,
}
