"""Cross-section loops to cap triangles: nesting, ear clipping with holes, repair, check.

The loops come from the kernels as segments labelled by loop and position.
Which loop lies inside which follows from the even-odd rule (a point is
inside a closed curve when a ray from it crosses the curve an odd number of
times; Shimrat 1962, Hormann and Agathos 2001): a loop enclosed by an even
number of others bounds material, an odd number makes it a hole of the
smallest loop around it. Each outer loop is triangulated with its holes by
mapbox earcut (Mapbox, ISC licence; ear clipping with hole bridging after
Eberly, *Triangulation by ear clipping*, 2002).

Earcut leaves out every vertex that is exactly collinear with its
neighbours, which the sections of meshes made on a grid are full of: the cap
would then span the vertex with one edge, leaving a T-junction and an open
mesh whose cap area still looks right; and where it has bridged a hole to
such a vertex before dropping it, part of the polygon is left uncovered. So
the exactly collinear vertices are taken out before earcut runs, and put
back after: the triangle spanning each run of them is split into a fan
through them. The caps are then checked edge by edge: together with the
loops they must use every edge once in each direction.
"""

from __future__ import annotations

import mapbox_earcut
import numpy as np
import warp as wp

from .._errors import MeshError
from .._parallel import launch
from . import _kernels

__all__ = ["cap_triangles", "relink_pinches"]


def _ring_next(starts: np.ndarray) -> np.ndarray:
    """Next position around its loop of every position of loops laid end to end at ``starts`` (L + 1,)."""
    nxt = np.arange(1, starts[-1] + 1, dtype=np.int64)
    nxt[starts[1:] - 1] = starts[:-1]
    return nxt


def _loop_areas(coords: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Signed area of each loop (shoelace; positive counter-clockwise)."""
    nxt = _ring_next(starts)
    cross = coords[:, 0] * coords[nxt, 1] - coords[nxt, 0] * coords[:, 1]
    return 0.5 * np.add.reduceat(cross, starts[:-1])


def _nesting(coords: np.ndarray, starts: np.ndarray, areas: np.ndarray, device, threads) -> tuple[np.ndarray, ...]:
    """(depth, parent) of every loop: how many loops enclose it, and the smallest one (-1: none)."""
    n_loops = len(starts) - 1
    lower = np.minimum.reduceat(coords, starts[:-1], axis=0)
    upper = np.maximum.reduceat(coords, starts[:-1], axis=0)
    depth = wp.empty(n_loops, dtype=wp.int32, device=device)
    parent = wp.empty(n_loops, dtype=wp.int32, device=device)
    inputs = [
        wp.array(coords, dtype=wp.vec2d, device=device),
        wp.array(starts.astype(np.int32), dtype=wp.int32, device=device),
        wp.array(lower, dtype=wp.vec2d, device=device),
        wp.array(upper, dtype=wp.vec2d, device=device),
        wp.array(areas, dtype=wp.float64, device=device),
    ]
    launch(_kernels.nesting_kernel, n_loops, inputs, [depth, parent], device, threads, min_chunk=16)
    return depth.numpy(), parent.numpy()  # host sync: the grouping of loops decides the earcut calls


def _edge_keys(tris: np.ndarray, n: int) -> np.ndarray:
    """Directed edge keys ``a * n + b`` of every triangle edge, (3 T,)."""
    t = tris.astype(np.int64)
    return (t * n + np.roll(t, -1, axis=1)).ravel()


def _corners(coords: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(N,) True for the loop vertices that are not exactly collinear with their neighbours.

    The test is earcut's own (its signed area of the three points is 0), run
    again on the loops left until no vertex fails it, as earcut itself would
    drop them one after another; a loop of three vertices is left whole.
    """
    n = len(coords)
    keep = np.ones(n, dtype=bool)
    loop_of = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
    while True:
        alive = np.flatnonzero(keep)
        first_alive = np.searchsorted(alive, starts[:-1])
        count = np.diff(np.searchsorted(alive, starts))
        rank = np.arange(len(alive)) - first_alive[loop_of[alive]]
        size = count[loop_of[alive]]
        nxt = alive[first_alive[loop_of[alive]] + (rank + 1) % size]
        prv = alive[first_alive[loop_of[alive]] + (rank - 1) % size]
        p, q, r = coords[prv], coords[alive], coords[nxt]
        flat = (q[:, 1] - p[:, 1]) * (r[:, 0] - q[:, 0]) - (q[:, 0] - p[:, 0]) * (r[:, 1] - q[:, 1]) == 0
        flat &= size > 3
        if not flat.any():
            return keep
        keep[alive[flat]] = False


def _repair(tris: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Put back the loop vertices that earcut skipped, by splitting the triangle that spans them.

    A run of skipped vertices ``d1 ... dk`` between used loop vertices ``a``
    and ``b`` is spanned by one triangle ``(a, b, c)``; it becomes the fan
    ``(a, d1, c), ..., (dk, b, c)`` (same orientation). A triangle may span
    runs on two or three of its edges: each round splits one run per
    triangle.

    Args:
        tris: (T, 3) triangles over loop positions.
        starts: (L + 1,) where each loop begins among the positions.

    Returns:
        (T', 3) triangles using every loop vertex.
    """
    n = int(starts[-1])
    nxt = _ring_next(starts)
    loop_of = np.repeat(np.arange(len(starts) - 1), np.diff(starts))
    size = np.diff(starts)[loop_of]
    while True:
        used = np.zeros(n, dtype=bool)
        used[tris.ravel()] = True
        if used.all():
            return tris
        kept = np.flatnonzero(used)
        # each run of skipped vertices, from the used vertex before it to the used vertex after it
        a = np.flatnonzero(used & ~used[nxt])
        at = np.searchsorted(kept, nxt[a])
        b = kept[np.minimum(at, len(kept) - 1)]
        wrap = (at >= len(kept)) | (loop_of[b] != loop_of[a])
        b = np.where(wrap, kept[np.searchsorted(kept, starts[loop_of[a]])], b)
        if np.any(loop_of[b] != loop_of[a]) or np.any(b == a):
            raise MeshError("slice: earcut left out a whole section loop (a degenerate or self-touching section)")
        keys = _edge_keys(tris, n)
        undirected = np.minimum(keys // n, keys % n) * n + np.maximum(keys // n, keys % n)
        order = np.argsort(undirected)
        ordered = undirected[order]
        span = np.minimum(a, b) * n + np.maximum(a, b)
        hit = np.searchsorted(ordered, span)
        if not np.all(ordered[np.minimum(hit, len(ordered) - 1)] == span):
            raise MeshError("slice: could not cap a section loop (skipped vertices with no triangle spanning them)")
        tri, first_run = np.unique(order[hit] // 3, return_index=True)
        a, b = a[first_run], b[first_run]
        corners = tris[tri]
        forward = ((corners[:, 0] == a) & (corners[:, 1] == b)) | ((corners[:, 1] == a) & (corners[:, 2] == b))
        forward |= (corners[:, 2] == a) & (corners[:, 0] == b)
        third = corners.sum(axis=1) - a - b
        length = (b - a) % size[a]  # loop edges from a to b
        which = np.repeat(np.arange(len(a)), length)
        step = np.arange(len(which)) - np.repeat(np.cumsum(length) - length, length)
        first = starts[loop_of[a]][which]
        p = first + (a[which] - first + step) % size[a][which]
        q = nxt[p]
        fan = np.where(forward[which][:, None], np.stack([p, q, third[which]], 1), np.stack([q, p, third[which]], 1))
        keep = np.ones(len(tris), dtype=bool)
        keep[tri] = False
        tris = np.concatenate([tris[keep], fan.astype(tris.dtype)])


def _check(tris: np.ndarray, starts: np.ndarray, points: np.ndarray, positions: np.ndarray) -> None:
    """MeshError unless the caps and the loops (run the loop way) use every edge once in each direction."""
    n = int(starts[-1])
    ring = np.arange(n) * n + _ring_next(starts)
    keys = np.concatenate([_edge_keys(tris, n), ring])
    unique, counts = np.unique(keys, return_counts=True)
    reverse = (unique % n) * n + unique // n
    found = np.searchsorted(unique, reverse)
    paired = unique[np.minimum(found, len(unique) - 1)] == reverse
    bad = np.flatnonzero((counts != 1) | ~paired)
    if len(bad):
        a = points[unique[bad[0]] // n]
        raise MeshError(
            "slice: the cap of a section loop does not close it near "
            f"{np.round(positions[a], 6).tolist()} (a self-intersecting mesh, or loops that touch)"
        )


def relink_pinches(
    previous: np.ndarray,
    starts: np.ndarray,
    start_order: np.ndarray,
    end_order: np.ndarray,
    start_point: np.ndarray,
    end_point: np.ndarray,
    coords: np.ndarray,
) -> np.ndarray:
    """Pair the segments in and out of each vertex where the section touches itself.

    The section lies on the right of its segments (its outer loops run
    clockwise), so around such a vertex the rays in and out alternate, and
    the way on from a segment coming in is the first ray out counter-clockwise
    from it: loops then touch at the vertex without crossing there.

    Args:
        previous: (S,) the segment before each one, as first linked.
        starts: (S,) start key of each segment.
        start_order, end_order: (S,) segments by start key and by end key.
        start_point, end_point: (S,) section point at each end of each segment.
        coords: (P, 2) plane coordinates of the section points.

    Returns:
        (S,) ``previous`` with the pairs at such vertices made again.
    """
    keys = starts[start_order]
    shared = np.r_[keys[1:] == keys[:-1], False] | np.r_[False, keys[1:] == keys[:-1]]
    j = np.flatnonzero(shared)
    group = np.cumsum(np.r_[True, keys[j][1:] != keys[j][:-1]]) - 1
    leaving, arriving = start_order[j], end_order[j]
    here = coords[start_point[leaving]]
    rays = np.concatenate([coords[end_point[leaving]] - here, coords[start_point[arriving]] - here])
    angle = np.arctan2(rays[:, 1], rays[:, 0])
    is_out = np.r_[np.ones(len(j), dtype=bool), np.zeros(len(j), dtype=bool)]
    segment = np.r_[leaving, arriving]
    groups = np.r_[group, group]
    order = np.lexsort((angle, groups))
    groups, is_out, segment = groups[order], is_out[order], segment[order]
    # the first ray out after each position, counter-clockwise, wrapping within its vertex
    outs = np.flatnonzero(is_out)
    after = np.searchsorted(outs, np.arange(len(order)), side="right")
    first_out = outs[np.searchsorted(groups[outs], groups)]
    following = np.where(after < len(outs), outs[np.minimum(after, len(outs) - 1)], -1)
    following = np.where((following >= 0) & (groups[np.maximum(following, 0)] == groups), following, first_out)
    coming = np.flatnonzero(~is_out)
    relinked = previous.copy()
    relinked[segment[following[coming]]] = segment[coming]
    return relinked


def cap_triangles(
    label: np.ndarray,
    distance: np.ndarray,
    start_point: np.ndarray,
    coords: np.ndarray,
    positions: np.ndarray,
    device,
    threads=None,
) -> tuple[np.ndarray, dict]:
    """Triangles closing the part below the plane, over section points.

    Args:
        label: (S,) loop label of each segment (its smallest segment id).
        distance: (S,) position of each segment along its loop.
        start_point: (S,) section point where each segment starts.
        coords: (P, 2) float64 plane coordinates of the section points
            (axes ``u``, ``v`` with ``u x v`` the plane normal).
        positions: (P, 3) positions of the section points (for messages).
        device: Warp device of the nesting kernel.
        threads: CPU threads (None: all).

    Returns:
        ``(triangles, facts)``: (C, 3) int64 point ids, counter-clockwise seen
        from below the plane's normal side where the loops run clockwise (so
        the cap closes the part below; reversed, the part above), and
        ``{"section_loops", "section_holes", "cap_area"}``.
    """
    order = np.lexsort((distance, label))
    points = start_point[order].astype(np.int64)
    loop_label = label[order]
    starts = np.flatnonzero(np.r_[True, loop_label[1:] != loop_label[:-1]])
    starts = np.append(starts, len(order))
    ring = coords[points]
    areas = _loop_areas(ring, starts)
    depth, parent = _nesting(ring, starts, areas, device, threads)
    hole = depth % 2 == 1
    group = np.where(hole, parent, np.arange(len(areas)))
    # loops regrouped: each outer loop followed by its holes, as earcut takes them
    loops = np.lexsort((hole, group))
    lengths = np.diff(starts)[loops]
    new_starts = np.concatenate([[0], np.cumsum(lengths)])
    take = np.arange(new_starts[-1]) + np.repeat(starts[loops] - new_starts[:-1], lengths)
    points, ring = points[take], ring[take]
    group_starts = np.flatnonzero(np.r_[True, group[loops][1:] != group[loops][:-1]])
    group_ends = np.append(group_starts[1:], len(loops))
    # earcut sees the loops without their exactly collinear vertices, and they are put back after
    kept = np.flatnonzero(_corners(ring, new_starts))
    kept_starts = np.searchsorted(kept, new_starts)
    pieces = []
    for g0, g1 in zip(group_starts, group_ends):
        base = kept_starts[g0]
        ends = (kept_starts[g0 + 1 : g1 + 1] - base).astype(np.uint32)
        local = mapbox_earcut.triangulate_float64(ring[kept[base : kept_starts[g1]]], ends)
        pieces.append(kept[local.astype(np.int64).reshape(-1, 3) + base])
    tris = np.concatenate(pieces) if pieces else np.zeros((0, 3), dtype=np.int64)
    tris = _repair(tris, new_starts)
    # the part below is capped against the way its loops run: flip each group whose
    # triangles turn the same way as its outer loop
    a, b, c = ring[tris[:, 0]], ring[tris[:, 1]], ring[tris[:, 2]]
    signed = 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    loop_at = np.repeat(np.arange(len(loops)), lengths)
    tri_group = np.searchsorted(group_starts, loop_at[tris[:, 0]], side="right") - 1
    outer_area = _loop_areas(ring, new_starts)[group_starts]
    total = np.bincount(tri_group, weights=signed, minlength=len(group_starts))
    flip = (np.sign(total) == np.sign(outer_area))[tri_group]
    tris[flip] = tris[flip][:, ::-1]
    _check(tris, new_starts, points, positions)
    facts = {"section_loops": len(areas), "section_holes": int(hole.sum()), "cap_area": float(np.abs(signed).sum())}
    return points[tris], facts
