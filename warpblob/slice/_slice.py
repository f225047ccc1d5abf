"""Planar slicing and capping of closed triangle meshes: a saw cut.

A plane splits a closed, consistently oriented triangle mesh into the part
below it (``dot(x - origin, normal) < 0``) and the part above, each closed
again by a cap over the cross-section. The orthopaedic saw of the
bone-surgery simulator in Boothroyd's 2011 MSc thesis (the source of this
library) capped the cut with a triangle fan around the section's centroid, which is wrong for every concave section and
for sections with holes (a hollow bone cut across gives two nested rings);
here the section is chained into loops, their nesting found by the even-odd
rule, and each outer loop triangulated with its holes by earcut (see
:mod:`warpblob.slice._section`).

Pipeline (Warp kernels, one thread per block of 1024 vertices or faces; one
host sync per stage): signed distances and the mesh's box; face
classification and counts; section segments, one per cut face, each running
the way its piece below walks the plane, keyed by the edge it crosses;
segment ends sorted by key (``radix_sort_pairs``) into section points and
linked end to start; pointer jumping labels the loops and orders them;
caps on the host (tiny: a few thousand points for a million triangles); the
halves emitted by the same block walk as the count.

Snapping: a vertex within ``snap`` times the diagonal of the mesh's box of
the plane is taken to lie on it, so no edge is cut within that distance of its end and no
sliver is made. The snapped vertex is not moved: the two halves share it,
their volumes still add up to the input's (to rounding), and each half's
volume differs from the exactly clipped one by at most the snap distance
times the area of the faces around the snapped vertices (its cap is planar
to within the snap distance).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from .._device import resolve_device
from .._errors import MeshError
from .._parallel import check_threads, launch
from .._stages import StageClock, compact, device_empty, scans, shared_array
from ..mesh import SurfaceMesh
from . import _kernels
from ._section import cap_triangles, relink_pinches

__all__ = ["slice", "SNAP", "CAP_COLOR"]

#: vertices within SNAP times the diagonal of the mesh's box of the plane count as on it
#: (float32 positions carry about 6e-8 of their magnitude: the window is a few
#: dozen of their steps)
SNAP = 1.0e-6
#: colour of the cap faces when no model gives one (bone, RGB in [0, 1])
CAP_COLOR = (0.89, 0.85, 0.72)

_NONE = np.iinfo(np.int32).max
#: smallest piece of a CPU launch over section items: a few thousand of them are one launch
_SMALL = 1 << 15


def _plane(origin, normal) -> tuple[np.ndarray, np.ndarray]:
    """(origin, unit normal) as float64 3-vectors, or MeshError naming the value."""
    try:
        o = np.asarray(origin, dtype=np.float64)
        n = np.asarray(normal, dtype=np.float64)
    except (TypeError, ValueError):
        raise MeshError(f"slice: the plane needs a 3-vector origin and normal, got {origin!r} and {normal!r}") from None
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise MeshError(f"slice: origin must be a finite 3-vector, got {origin!r}")
    if n.shape != (3,) or not np.all(np.isfinite(n)):
        raise MeshError(f"slice: normal must be a finite 3-vector, got {normal!r}")
    length = float(np.linalg.norm(n))
    if not length > 0.0:
        raise MeshError(f"slice: normal must be non-zero, got {normal!r}")
    return o, n / length


def _axes(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit axes (u, v) of the plane with ``u x v = n`` (exact for axis-aligned normals)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def _arrays(mesh) -> tuple[np.ndarray, ...]:
    """(vertices, faces, normals, colors) of ``mesh`` as contiguous float32 / int32, or MeshError."""
    if not isinstance(mesh, SurfaceMesh):
        raise MeshError(f"slice: expected a SurfaceMesh, got {type(mesh).__name__}")
    v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    f = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    nv = np.ascontiguousarray(mesh.normals, dtype=np.float32)
    c = np.ascontiguousarray(mesh.colors, dtype=np.float32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"slice: vertices must be (V, 3) and faces (F, 3), got {v.shape} and {f.shape}")
    if nv.shape != v.shape or c.shape != v.shape:
        raise MeshError(
            f"slice: normals and colors must be (V, 3) like the vertices {v.shape}, got {nv.shape} and {c.shape}"
        )
    return v, f, nv, c


_TABLES: dict = {}


def _table(device) -> wp.array:
    """The face-code table (:func:`~warpblob.slice._kernels.face_codes`) on ``device``, made once."""
    if device.alias not in _TABLES:
        _TABLES[device.alias] = wp.array(_kernels.face_codes(), dtype=wp.int8, device=device)
    return _TABLES[device.alias]


def _head(a: wp.array, n: int) -> wp.array:
    """The first ``n`` items of ``a`` (Warp refuses an empty slice: then ``a`` itself, unused)."""
    return a[:n] if n else a


def _edge_text(vertices: np.ndarray, a: int, b: int) -> str:
    return f"edge ({a}, {b}) from {np.round(vertices[a], 6).tolist()} to {np.round(vertices[b], 6).tolist()}"


def _open_edge(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Describe the first face edge (in face order) that keeps ``faces`` from being closed and oriented."""
    f = faces.astype(np.int64)
    n = len(vertices)
    at, to = f.ravel(), np.roll(f, -1, axis=1).ravel()
    directed = at * n + to
    order = np.argsort(directed, kind="stable")
    ordered = directed[order]
    twice = np.zeros(len(directed), dtype=bool)
    same = ordered[1:] == ordered[:-1]
    twice[order[1:][same]] = True
    twice[order[:-1][same]] = True
    found = np.searchsorted(ordered, to * n + at)
    lonely = ordered[np.minimum(found, len(ordered) - 1)] != to * n + at
    corner = int(np.flatnonzero(twice | lonely)[0])
    edge = _edge_text(vertices, int(at[corner]), int(to[corner]))
    if twice[corner]:
        return f"{edge} of face {corner // 3} is run the same way by two faces (flipped faces, or more faces on it)"
    return f"{edge} of face {corner // 3} has no face running it the other way (an open boundary)"


def _key_text(vertices: np.ndarray, key: int) -> str:
    n = len(vertices)
    a, b = key // n, key % n
    return f"vertex {a} at {np.round(vertices[a], 6).tolist()}" if a == b else _edge_text(vertices, a, b)


def _empty(stats: dict) -> SurfaceMesh:
    z = np.zeros((0, 3), dtype=np.float32)
    mesh = SurfaceMesh(z, np.zeros((0, 3), dtype=np.int32), z, z, stats)
    mesh.is_cap = np.zeros(0, dtype=bool)
    mesh.cap_colors = z
    return mesh


def slice(
    mesh: SurfaceMesh,
    origin=None,
    normal=None,
    *,
    planes=None,
    cap: bool = True,
    cap_color=CAP_COLOR,
    model=None,
    snap: float = SNAP,
    device=None,
    threads: int | None = None,
):
    """Cut a closed triangle mesh by a plane into two closed, capped halves.

    Args:
        mesh: a closed, consistently oriented :class:`~warpblob.mesh.SurfaceMesh`
            (any closed mesh with ``cap=False``); never modified.
        origin: (3,) a point of the plane, model units.
        normal: (3,) the plane's normal (any length but 0); "above" is the side
            it points to.
        planes: instead of ``origin``/``normal``, a sequence of ``(origin,
            normal)`` pairs: the mesh is cut by each plane in turn.
        cap: close each half over the section. False cuts without caps and
            takes open meshes too.
        cap_color: (3,) RGB in [0, 1] of the cap faces when ``model`` is None.
        model: the BlobTree the mesh was made from: caps take its colour field
            at each cap triangle's centroid.
        snap: vertices within ``snap`` times the diagonal of the mesh's box of
            the plane count as on it (see the module docstring for what that does to
            volumes).
        device: Warp device (default: Warp's default device).
        threads: CPU threads of the kernels (default: all cores).

    Returns:
        With one plane ``(below, above)``, two :class:`~warpblob.mesh.SurfaceMesh`:
        the part where ``dot(x - origin, normal) < 0`` and the rest, each closed
        and oriented when ``mesh`` is, with ``is_cap`` ((F,) bool: faces of
        caps, old ones included) and ``cap_colors`` ((C, 3) float32, the cap
        faces' colours in face order); new vertices where the plane cuts an
        edge, with normals and colours interpolated along it. Either may have
        no faces. With ``planes``, the list of non-empty pieces.

    Raises:
        MeshError: a bad plane or mesh array, a face with an index out of
            range or a repeated vertex, a non-finite vertex; with ``cap``, an
            open or inconsistently oriented mesh (naming the first bad edge)
            or a section that cannot be closed (an edge of more than two faces
            on the plane, a self-intersecting mesh).

    Example:
        >>> import numpy as np, warpblob as wb
        >>> from warpblob.slice import slice
        >>> ball = wb.polygonize(wb.Point((0, 0, 0), 1.0), cellsize=0.1)
        >>> below, above = slice(ball, (0, 0, 0.1), (0, 0, 1))
        >>> below.is_closed_manifold(), above.is_closed_manifold()
        (True, True)
        >>> bool(abs(below.volume() + above.volume() - ball.volume()) < 1e-6 * ball.volume())
        True
    """
    check_threads(threads)
    if not (isinstance(snap, (int, float)) and math.isfinite(snap) and snap >= 0):
        raise MeshError(f"slice: snap must be a finite number >= 0, got {snap!r}")
    color = np.asarray(cap_color, dtype=np.float32)
    if color.shape != (3,) or not np.all(np.isfinite(color)):
        raise MeshError(f"slice: cap_color must be an RGB triple, got {cap_color!r}")
    if planes is None:
        cut = [_plane(origin, normal)]
    else:
        if origin is not None or normal is not None:
            raise MeshError("slice: give either origin and normal or planes, not both")
        try:
            cut = [_plane(o, n) for o, n in planes]
        except (TypeError, ValueError):
            raise MeshError(f"slice: planes must be (origin, normal) pairs, got {planes!r}") from None
        if not cut:
            raise MeshError("slice: planes is empty")
    dev = resolve_device(device)
    pieces = [mesh]
    for o, n in cut:
        halves = []
        for piece in pieces:
            halves.extend(_slice_one(piece, o, n, cap, color, model, float(snap), dev, threads))
        pieces = [p for p in halves if p.face_count] if planes is not None else halves
    return pieces if planes is not None else tuple(pieces)


def _slice_one(mesh, o, n, cap, color, model, snap, dev, threads) -> tuple[SurfaceMesh, SurfaceMesh]:
    """(below, above) of one plane; arguments checked."""
    vertices, faces, normals, colors = _arrays(mesh)
    old_caps = mesh.is_cap
    if old_caps is not None:
        old_caps = np.asarray(old_caps, dtype=bool)
        if old_caps.shape != (len(faces),):
            raise MeshError(f"slice: is_cap must be ({len(faces)},) like the faces, got {old_caps.shape}")
    clock = StageClock(dev, "slice", 5)
    stats = {"plane_origin": o.tolist(), "plane_normal": n.tolist()}
    n_v, n_f = len(vertices), len(faces)
    if n_v == 0 or n_f == 0:
        return _empty(dict(stats)), _empty(dict(stats))
    lap = clock.lap
    positions = shared_array(vertices, wp.vec3, dev)
    triangles = shared_array(faces, wp.vec3i, dev)
    origin_d, normal_d = wp.vec3d(*o), wp.vec3d(*n)
    vb = -(-n_v // _kernels.BLOCK)
    fb = -(-n_f // _kernels.BLOCK)

    # 1. distances and the box that sizes the snap distance
    distances = device_empty(n_v, wp.float32, dev)
    lower, upper = device_empty(vb, wp.vec3, dev), device_empty(vb, wp.vec3, dev)
    vbad = device_empty(vb, wp.int32, dev)
    launch(
        _kernels.distance_kernel, vb, [positions, origin_d, normal_d], [distances, lower, upper, vbad], dev, threads, 1
    )
    bad = vbad.numpy()  # host sync: the box sizes the snap distance
    if np.any(bad >= 0):
        i = int(bad[bad >= 0].min())
        raise MeshError(f"slice: vertex {i} is not finite: {vertices[i].tolist()}")
    diagonal = float(np.linalg.norm(upper.numpy().max(axis=0).astype(np.float64) - lower.numpy().min(axis=0)))
    eps = snap * diagonal

    # 2. classify faces, count the output of each block
    codes = device_empty(n_f, wp.int8, dev)
    counts = [device_empty(fb, wp.int32, dev) for _ in range(4)]
    used_below, used_above = device_empty(n_v, wp.int8, dev, zero=True), device_empty(n_v, wp.int8, dev, zero=True)
    prints, fbad = device_empty(fb, wp.uint64, dev), device_empty(fb, wp.int32, dev)
    launch(
        _kernels.classify_kernel, fb, [triangles, distances, positions, _table(dev), normal_d, eps],
        [codes, *counts, used_below, used_above, prints, fbad], dev, threads, 1,
    )  # fmt: skip
    keep_counts = [device_empty(vb, wp.int32, dev) for _ in range(3)]
    launch(_kernels.keep_count_kernel, vb, [distances, used_below, used_above, eps], keep_counts, dev, threads, 1)
    # host sync: every count of the stage, and the checks
    offsets, totals = scans(*counts, *keep_counts[:2])
    below_offsets, above_offsets, segment_offsets, record_offsets, keep_below_offsets, keep_above_offsets = offsets
    n_below, n_above, n_segments, n_records, kept_below, kept_above = totals
    bad = fbad.numpy()
    if np.any(bad >= 0):
        i = int(bad[bad >= 0].min())
        raise MeshError(f"slice: face {i} = {faces[i].tolist()} has an index out of [0, {n_v}) or a repeated vertex")
    if cap and int(prints.numpy().sum(dtype=np.uint64)) != 0:
        edge = _open_edge(vertices, faces)
        raise MeshError(f"slice: the mesh is not closed and oriented: {edge}; use cap=False to cut it open")
    stats.update(snap_distance=eps, snapped_vertices=int(keep_counts[2].numpy().sum()))
    lap("classify")

    # 3. section segments: one per cut face; with caps, in-plane edges whose faces lie on both sides
    records = cap and n_records > 0
    room = n_segments + (n_records // 2 + 1 if records else 0)
    starts, ends = device_empty(room, wp.int64, dev), device_empty(room, wp.int64, dev)
    record_keys = device_empty(2 * n_records if records else 0, wp.int64, dev)
    record_edges = device_empty(n_records if records else 0, wp.vec3i, dev)
    launch(
        _kernels.section_kernel, fb,
        [triangles, codes, distances, eps, counts[2], segment_offsets, counts[3], record_offsets, int(records)],
        [starts, ends, record_keys, record_edges], dev, threads, 1,
    )  # fmt: skip
    if records:
        order = wp.array(np.arange(2 * n_records, dtype=np.int32), device=dev)
        wp.utils.radix_sort_pairs(record_keys, order, n_records)
        n_pairs = (n_records + 1) // 2
        boundary = device_empty(n_pairs, wp.int32, dev)
        pair_bad = wp.full(1, _NONE, dtype=wp.int32, device=dev)
        launch(
            _kernels.plane_edge_kernel, n_pairs, [record_keys, order, record_edges, n_records], [boundary, pair_bad],
            dev, threads, _SMALL,
        )  # fmt: skip
        pairs = compact(boundary, dev, threads)  # host sync: the number of in-plane section segments
        i = int(pair_bad.numpy()[0])
        if i != _NONE:
            key = int(record_keys.numpy()[2 * i])
            where = _key_text(vertices, key)
            raise MeshError(f"slice: {where} lies in the plane and is not shared by exactly two faces")
        launch(
            _kernels.plane_segment_kernel, pairs.shape[0], [pairs, order, record_edges, n_v, n_segments],
            [starts, ends], dev, threads, _SMALL,
        )  # fmt: skip
        n_segments += pairs.shape[0]

    # 4. section points: segment ends sorted by key, one point per key
    s = n_segments
    keys, values = device_empty(4 * s, wp.int64, dev), device_empty(4 * s, wp.int32, dev)
    launch(_kernels.endpoint_kernel, s, [_head(starts, s), _head(ends, s)], [keys, values], dev, threads, _SMALL)
    wp.utils.radix_sort_pairs(keys, values, 2 * s)
    flags = [device_empty(2 * s, wp.int32, dev) for _ in range(3)]
    launch(_kernels.point_heads_kernel, 2 * s, [_head(keys, 2 * s), values, n_v, s], flags, dev, threads, _SMALL)
    # host sync: the point counts size the point arrays and the new vertices
    (head_offsets, crossing_offsets, start_offsets), (n_points, n_crossing, _) = scans(*flags)
    start_point, end_point = device_empty(s, wp.int32, dev), device_empty(s, wp.int32, dev)
    point_keys, crossing_rank = device_empty(n_points, wp.int64, dev), device_empty(n_points, wp.int32, dev)
    start_order, end_order = device_empty(s, wp.int32, dev), device_empty(s, wp.int32, dev)
    launch(
        _kernels.point_ids_kernel, 2 * s,
        [keys, values, flags[0], head_offsets, flags[1], crossing_offsets, start_offsets, s],
        [start_point, end_point, point_keys, crossing_rank, start_order, end_order], dev, threads, _SMALL,
    )  # fmt: skip
    n_out_below, n_out_above = kept_below + n_crossing, kept_above + n_crossing
    out = {
        side: [device_empty(count, wp.vec3, dev) for _ in range(3)]
        for side, count in (("below", n_out_below), ("above", n_out_above))
    }
    u, v = _axes(n)
    coords = device_empty(n_points, wp.vec2d, dev)
    normals_d, colors_d = shared_array(normals, wp.vec3, dev), shared_array(colors, wp.vec3, dev)
    launch(
        _kernels.point_kernel, n_points,
        [point_keys, crossing_rank, positions, normals_d, colors_d, origin_d, normal_d, wp.vec3d(*u), wp.vec3d(*v),
         kept_below, kept_above],
        [*out["below"], *out["above"], coords], dev, threads, _SMALL,
    )  # fmt: skip
    lap("section")

    # 5. loops: link each segment to the next, label and order them by pointer jumping; caps
    cap_points = np.zeros((0, 3), dtype=np.int64)
    facts = {"section_loops": 0, "section_holes": 0, "cap_area": 0.0}
    if cap and s:
        previous = device_empty(s, wp.int32, dev)
        link_bad = wp.full(1, _NONE, dtype=wp.int32, device=dev)
        pinched = wp.zeros(1, dtype=wp.int32, device=dev)
        launch(
            _kernels.link_kernel, s, [_head(starts, s), ends, start_order, end_order, n_v],
            [previous, link_bad, pinched], dev, threads, _SMALL,
        )  # fmt: skip
        j = int(link_bad.numpy()[0])  # host sync: an open section stops here
        if j != _NONE:
            k = min(int(starts.numpy()[start_order.numpy()[j]]), int(ends.numpy()[end_order.numpy()[j]]))
            raise MeshError(
                f"slice: the section is not closed at {_key_text(vertices, k)}: an open mesh or an edge of more "
                "than two faces there; use cap=False to cut it open"
            )
        if pinched.numpy()[0]:
            previous.assign(
                relink_pinches(
                    previous.numpy(), starts.numpy()[:s], start_order.numpy(), end_order.numpy(), start_point.numpy(),
                    end_point.numpy(), coords.numpy(),
                )
            )
        label = wp.array(np.arange(s, dtype=np.int32), device=dev)
        distance = device_empty(s, wp.int32, dev, zero=True)
        spare = [device_empty(s, wp.int32, dev) for _ in range(3)]
        step = 1
        while step < s:
            launch(_kernels.jump_kernel, s, [previous, label, distance, step], spare, dev, threads, _SMALL)
            spare, (previous, label, distance) = [previous, label, distance], spare
            step *= 2
        lap("loops")
        # host sync: the loops go to earcut on the host
        rank = crossing_rank.numpy()
        point_positions = np.where(
            (rank >= 0)[:, None], out["below"][0].numpy()[kept_below + rank], vertices[point_keys.numpy() // n_v]
        )
        cap_points, facts = cap_triangles(
            label.numpy(), distance.numpy(), start_point.numpy(), coords.numpy(), point_positions, dev, threads
        )
        lap("caps")

    # 6. the halves: kept vertices, cut faces, caps
    maps = [device_empty(n_v, wp.int32, dev) for _ in range(2)]
    launch(
        _kernels.keep_kernel, vb,
        [distances, used_below, used_above, positions, normals_d, colors_d, eps, keep_below_offsets,
         keep_above_offsets],
        [*maps, *out["below"], *out["above"]], dev, threads, 1,
    )  # fmt: skip
    faces_below = device_empty(n_below + len(cap_points), wp.vec3i, dev)
    faces_above = device_empty(n_above + len(cap_points), wp.vec3i, dev)
    sources = [device_empty(count if old_caps is not None else 0, wp.int32, dev) for count in (n_below, n_above)]
    launch(
        _kernels.face_kernel, fb,
        [triangles, codes, positions, below_offsets, above_offsets, segment_offsets, *maps, start_point, end_point,
         crossing_rank, kept_below, kept_above, out["below"][0], int(old_caps is not None)],
        [faces_below, faces_above, *sources], dev, threads, 1,
    )  # fmt: skip
    point_index = [device_empty(n_points, wp.int32, dev) for _ in range(2)]
    launch(
        _kernels.point_index_kernel, n_points, [point_keys, crossing_rank, *maps, kept_below, kept_above],
        point_index, dev, threads, _SMALL,
    )  # fmt: skip
    if len(cap_points) and model is not None:
        from ..field import color as field_color

        corners = out["below"][0].numpy()[point_index[0].numpy()[cap_points]]
        cap_rgb = np.asarray(field_color(model, corners.mean(axis=1), device=dev), dtype=np.float32)
    else:
        cap_rgb = np.broadcast_to(color, (len(cap_points), 3))
    lap("output")
    stats.update(facts)
    stats.update(section_points=n_points, section_segments=s, seconds=clock.seconds)
    stats["total_seconds"] = sum(clock.seconds.values())
    track = old_caps is not None
    old_rank = np.cumsum(old_caps) - 1 if track else None
    results = []
    for faces_out, n_kept_faces, index, attributes, src, reverse in (
        (faces_below, n_below, point_index[0], out["below"], sources[0], False),
        (faces_above, n_above, point_index[1], out["above"], sources[1], True),
    ):
        f_out = faces_out.numpy()
        caps = index.numpy()[cap_points]
        f_out[n_kept_faces:] = caps[:, ::-1] if reverse else caps
        p, nn, cc = (a.numpy() for a in attributes)
        facts = {"triangles": len(f_out), "vertices": len(p), "cap_triangles": len(cap_points)}
        piece = SurfaceMesh(p, f_out, nn, cc, {**stats, **facts})
        is_cap = np.zeros(len(f_out), dtype=bool)
        is_cap[n_kept_faces:] = True
        cap_colors = np.asarray(cap_rgb, dtype=np.float32)
        if track:
            # faces cut from earlier caps stay caps, with their colours
            origin_face = src.numpy()
            was_cap = old_caps[origin_face]
            is_cap[:n_kept_faces] = was_cap
            cap_colors = np.concatenate([np.asarray(mesh.cap_colors)[old_rank[origin_face[was_cap]]], cap_colors])
        piece.is_cap = is_cap
        piece.cap_colors = np.ascontiguousarray(cap_colors, dtype=np.float32)
        results.append(piece)
    return tuple(results)
