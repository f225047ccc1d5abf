"""Warp functions and kernels that evaluate a linearized BlobTree.

The traversal is stackless in the sense of the thesis (SPEC 1.5): no
recursion, and per-thread storage bounded by constants that do not grow with
the tree (:data:`~warpblob._linearize.SLOTS` registers for open operators,
:data:`~warpblob._linearize.WARP_NESTING` saved points for open warps). It
walks the pre-order node array with ``skip``/``parent`` links; a node whose
box does not hold the point is skipped with its whole subtree (exactly 0),
and wide sparse operators visit only the operands listed in the point's grid
cell. Value, analytic gradient and colour are computed together.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .._linearize import SLOTS, WARP_NESTING
from ..tree import _kinds

mat34 = wp.types.matrix(shape=(3, 4), dtype=wp.float32)
vec_slots = wp.types.vector(length=SLOTS, dtype=wp.float32)
ivec_slots = wp.types.vector(length=SLOTS, dtype=wp.int32)
mat_slots3 = wp.types.matrix(shape=(SLOTS, 3), dtype=wp.float32)
mat_warps3 = wp.types.matrix(shape=(WARP_NESTING, 3), dtype=wp.float32)
# (value, gradient, colour) of one evaluation, padded to 8 floats: a 28-byte vector
# compiles to overlapping 16-byte moves that defeat store forwarding on x86
vec7 = wp.types.vector(length=8, dtype=wp.float32)

K_POINT = wp.constant(_kinds.POINT)
K_SEGMENT = wp.constant(_kinds.SEGMENT)
K_DISC = wp.constant(_kinds.DISC)
K_RING = wp.constant(_kinds.RING)
K_CONE = wp.constant(_kinds.CONE)
K_POLYGON = wp.constant(_kinds.POLYGON)
K_BOX = wp.constant(_kinds.BOX)
K_INFLATE = wp.constant(_kinds.INFLATE)
K_REVOLVE = wp.constant(_kinds.REVOLVE)
K_PRIM_END = wp.constant(_kinds.PRIMITIVE_KIND_END)
K_BLEND = wp.constant(_kinds.BLEND)
K_UNION = wp.constant(_kinds.UNION)
K_INTERSECTION = wp.constant(_kinds.INTERSECTION)
K_SMOOTH = wp.constant(_kinds.SMOOTH_BLEND)
K_TWIST = wp.constant(_kinds.TWIST)
K_TAPER = wp.constant(_kinds.TAPER)


@wp.struct
class ModelArrays:
    """Device view of a :class:`~warpblob._linearize.LinearModel`."""

    kind: wp.array(dtype=wp.int32)
    skip: wp.array(dtype=wp.int32)
    parent: wp.array(dtype=wp.int32)
    ref: wp.array(dtype=wp.int32)
    lower: wp.array(dtype=wp.vec3)
    upper: wp.array(dtype=wp.vec3)
    params: wp.array(dtype=wp.vec4)
    inverse: wp.array(dtype=mat34)
    stretch: wp.array(dtype=wp.float32)
    radius: wp.array(dtype=wp.float32)
    color: wp.array(dtype=wp.vec3)
    data_start: wp.array(dtype=wp.int32)
    data: wp.array(dtype=wp.float32)
    grid_lower: wp.array(dtype=wp.vec3)
    grid_inv_cell: wp.array(dtype=wp.vec3)
    grid_dims: wp.array(dtype=wp.vec3i)
    grid_base: wp.array(dtype=wp.int32)
    cell_offsets: wp.array(dtype=wp.int32)
    cell_items: wp.array(dtype=wp.int32)


# --------------------------------------------------------------------------
# input checks


@wp.func
def smallest(v: wp.vec3):
    return wp.min(wp.min(v[0], v[1]), v[2])


@wp.func
def smallest(v: float):  # noqa: F811 (a Warp overload of the vec3 version)
    return v


@wp.kernel(enable_backward=False)
def find_bad_entry_kernel(values: wp.array(dtype=Any), lowest: float, first: wp.array(dtype=wp.int32)):
    """``first[0] = min(first[0], i)`` over entries ``values[i]`` (vec3 or
    float32) that are not finite or have a component below ``lowest``."""
    i = wp.tid()
    v = values[i]
    if not wp.isfinite(v) or smallest(v) < lowest:
        wp.atomic_min(first, 0, i)


# both overloads declared up front: the module then compiles once, whichever input comes first
wp.overload(find_bad_entry_kernel, {"values": wp.array(dtype=wp.vec3)})
wp.overload(find_bad_entry_kernel, {"values": wp.array(dtype=wp.float32)})


# --------------------------------------------------------------------------
# small helpers


@wp.func
def safe_div3(v: wp.vec3, d: float):
    if d > 0.0:
        return v / d
    return wp.vec3(0.0)


@wp.func
def dist_result(v: wp.vec3):
    """(d, grad d) from the vector between the point and its closest skeleton point."""
    d = wp.length(v)
    g = safe_div3(v, d)
    return wp.vec4(d, g[0], g[1], g[2])


@wp.func
def closest_on_segment2(p: wp.vec2, a: wp.vec2, b: wp.vec2):
    ab = b - a
    den = wp.dot(ab, ab)
    t = float(0.0)
    if den > 0.0:
        t = wp.clamp(wp.dot(p - a, ab) / den, 0.0, 1.0)
    return a + t * ab


@wp.func
def apply_inverse(m: mat34, p: wp.vec3):
    return wp.vec3(
        m[0, 0] * p[0] + m[0, 1] * p[1] + m[0, 2] * p[2] + m[0, 3],
        m[1, 0] * p[0] + m[1, 1] * p[1] + m[1, 2] * p[2] + m[1, 3],
        m[2, 0] * p[0] + m[2, 1] * p[1] + m[2, 2] * p[2] + m[2, 3],
    )


@wp.func
def pull_gradient(m: mat34, g: wp.vec3):
    """Gradient in the parent frame from a local gradient: A^T g."""
    return wp.vec3(
        m[0, 0] * g[0] + m[1, 0] * g[1] + m[2, 0] * g[2],
        m[0, 1] * g[0] + m[1, 1] * g[1] + m[2, 1] * g[2],
        m[0, 2] * g[0] + m[1, 2] * g[1] + m[2, 2] * g[2],
    )


@wp.func
def inside_box(p: wp.vec3, lo: wp.vec3, hi: wp.vec3):
    return p[0] >= lo[0] and p[0] <= hi[0] and p[1] >= lo[1] and p[1] <= hi[1] and p[2] >= lo[2] and p[2] <= hi[2]


# --------------------------------------------------------------------------
# distances to canonical skeletons: (d, dd/dx, dd/dy, dd/dz) in the local frame


@wp.func
def point_offset(x: wp.vec3, prm: wp.vec4):
    """Vector from the nearest point of a point skeleton to ``x`` (local frame)."""
    return x


@wp.func
def segment_offset(x: wp.vec3, prm: wp.vec4):
    """Vector from the nearest point of a segment skeleton (local x, length ``prm[0]``)."""
    return x - wp.vec3(wp.clamp(x[0], 0.0, prm[0]), 0.0, 0.0)


@wp.func
def cone_offset(x: wp.vec3, prm: wp.vec4):
    """Vector from the nearest point of a solid cone skeleton (``prm``: length
    along local z, radius ``ra`` at z = 0, ``rb`` at the top), 0 inside. The
    branches are selections, so loops over points have none (array mode)."""
    length = prm[0]
    ra = prm[1]
    rb = prm[2]
    rho = wp.sqrt(x[0] * x[0] + x[1] * x[1])
    z = x[2]
    p = wp.vec2(rho, z)
    c = closest_on_segment2(p, wp.vec2(0.0, 0.0), wp.vec2(ra, 0.0))
    best = wp.length_sq(p - c)
    c2 = closest_on_segment2(p, wp.vec2(ra, 0.0), wp.vec2(rb, length))
    d2 = wp.length_sq(p - c2)
    c = wp.where(d2 < best, c2, c)
    best = wp.where(d2 < best, d2, best)
    c3 = closest_on_segment2(p, wp.vec2(rb, length), wp.vec2(0.0, length))
    c = wp.where(wp.length_sq(p - c3) < best, c3, c)
    v = p - c
    radial = safe_div3(wp.vec3(x[0], x[1], 0.0), rho)
    inside = z >= 0.0 and z <= length and rho <= ra + (rb - ra) * z / length
    return wp.where(inside, wp.vec3(0.0), wp.vec3(v[0] * radial[0], v[0] * radial[1], v[1]))


@wp.func
def dist_polygon(x: wp.vec3, data: wp.array(dtype=wp.float32), start: int, n: int):
    p = wp.vec2(x[0], x[1])
    inside = bool(False)
    best = float(1.0e30)
    close = p
    j = n - 1
    for i in range(n):
        a = wp.vec2(data[start + 2 * i], data[start + 2 * i + 1])
        b = wp.vec2(data[start + 2 * j], data[start + 2 * j + 1])
        if (a[1] > p[1]) != (b[1] > p[1]):
            xc = a[0] + (p[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
            if p[0] < xc:
                inside = not inside
        c = closest_on_segment2(p, a, b)
        d2 = wp.length_sq(p - c)
        if d2 < best:
            best = d2
            close = c
        j = i
    v = wp.vec2(0.0)
    if not inside:
        v = p - close
    return dist_result(wp.vec3(v[0], v[1], x[2]))


@wp.func
def box_offset(x: wp.vec3, prm: wp.vec4):
    """Vector from the nearest point of a box skeleton (half sizes ``prm[0:3]``)."""
    return wp.vec3(
        wp.max(wp.abs(x[0]) - prm[0], 0.0) * wp.sign(x[0]),
        wp.max(wp.abs(x[1]) - prm[1], 0.0) * wp.sign(x[1]),
        wp.max(wp.abs(x[2]) - prm[2], 0.0) * wp.sign(x[2]),
    )


@wp.func
def sketch_outside(u: wp.vec2, data: wp.array(dtype=wp.float32), start: int):
    """(o, do/du) with o = max(-s(u), e(u), 0): s the thin-plate spline, e the
    distance to the contour's bounding rectangle."""
    m = int(data[start])
    lo = wp.vec2(data[start + 1], data[start + 2])
    hi = wp.vec2(data[start + 3], data[start + 4])
    s = data[start + 6] * u[0] + data[start + 7] * u[1] + data[start + 8]
    gs = wp.vec2(data[start + 6], data[start + 7])
    base = start + 9
    for i in range(m):
        c = wp.vec2(data[base + 3 * i], data[base + 3 * i + 1])
        w = data[base + 3 * i + 2]
        v = u - c
        r2 = wp.dot(v, v)
        if r2 > 0.0:
            lnr = 0.5 * wp.log(r2)
            s += w * r2 * lnr
            gs += (w * (2.0 * lnr + 1.0)) * v
    ev = wp.vec2(wp.max(lo[0] - u[0], 0.0) - wp.max(u[0] - hi[0], 0.0), wp.max(lo[1] - u[1], 0.0) - wp.max(u[1] - hi[1], 0.0))
    e = wp.length(ev)
    o = float(0.0)
    go = wp.vec2(0.0)
    if -s > o:
        o = -s
        go = -gs
    if e > o:
        o = e
        go = -ev / e
    return wp.vec4(o, go[0], go[1], s), gs


@wp.func
def dist_inflate(x: wp.vec3, thickness: float, data: wp.array(dtype=wp.float32), start: int):
    res, gs = sketch_outside(wp.vec2(x[0], x[1]), data, start)
    depth = data[start + 5]
    t = res[3] / depth
    h = float(0.0)
    gh = wp.vec2(0.0)
    if t > 0.0:
        tc = wp.min(t, 1.0)
        h = thickness * (1.0 - (1.0 - tc) * (1.0 - tc))
        if t < 1.0:
            gh = (thickness * 2.0 * (1.0 - t) / depth) * gs
    az = wp.abs(x[2])
    hz = wp.max(az - h, 0.0)
    d = wp.sqrt(res[0] * res[0] + hz * hz)
    if d <= 0.0:
        return wp.vec4(0.0)
    gx = res[0] * res[1]
    gy = res[0] * res[2]
    gz = float(0.0)
    if hz > 0.0:
        gx -= hz * gh[0]
        gy -= hz * gh[1]
        gz = hz * wp.sign(x[2])
    return wp.vec4(d, gx / d, gy / d, gz / d)


@wp.func
def dist_revolve(x: wp.vec3, data: wp.array(dtype=wp.float32), start: int):
    rho = wp.sqrt(x[0] * x[0] + x[1] * x[1])
    res, gs = sketch_outside(wp.vec2(rho, x[2]), data, start)
    radial = safe_div3(wp.vec3(x[0], x[1], 0.0), rho)
    return wp.vec4(res[0], res[1] * radial[0], res[1] * radial[1], res[2])


@wp.func
def dist_sweep(x: wp.vec3, data: wp.array(dtype=wp.float32), start: int):
    m = int(data[start])
    seg = start + 9 + 3 * m
    count = int(data[seg])
    best = wp.vec4(1.0e30, 0.0, 0.0, 0.0)
    for k in range(count):
        b = seg + 1 + 13 * k
        inv = mat34(
            data[b + 0], data[b + 1], data[b + 2], data[b + 3],
            data[b + 4], data[b + 5], data[b + 6], data[b + 7],
            data[b + 8], data[b + 9], data[b + 10], data[b + 11],
        )  # fmt: skip
        length = data[b + 12]
        y = apply_inverse(inv, x)
        res, gs = sketch_outside(wp.vec2(y[0], y[1]), data, start)
        a = wp.max(wp.max(-y[2], y[2] - length), 0.0)
        sa = float(0.0)
        if y[2] > length:
            sa = 1.0
        elif y[2] < 0.0:
            sa = -1.0
        d = wp.sqrt(res[0] * res[0] + a * a)
        if d < best[0]:
            g = wp.vec3(0.0)
            if d > 0.0:
                g = pull_gradient(inv, wp.vec3(res[0] * res[1], res[0] * res[2], a * sa) / d)
            best = wp.vec4(d, g[0], g[1], g[2])
    return best


@wp.func
def primitive_distance(kind: int, x: wp.vec3, prm: wp.vec4, data: wp.array(dtype=wp.float32), start: int):
    if kind == K_POINT:
        return dist_result(point_offset(x, prm))
    if kind == K_SEGMENT:
        return dist_result(segment_offset(x, prm))
    if kind == K_DISC or kind == K_RING:
        rho = wp.sqrt(x[0] * x[0] + x[1] * x[1])
        dr = rho - prm[0]
        if kind == K_DISC:
            dr = wp.max(dr, 0.0)
        # on the axis every radial direction is equally near: take +x
        radial = wp.vec3(1.0, 0.0, 0.0)
        if rho > 0.0:
            radial = wp.vec3(x[0], x[1], 0.0) / rho
        return dist_result(wp.vec3(dr * radial[0], dr * radial[1], x[2]))
    if kind == K_CONE:
        return dist_result(cone_offset(x, prm))
    if kind == K_POLYGON:
        return dist_polygon(x, data, start, int(prm[0]))
    if kind == K_BOX:
        return dist_result(box_offset(x, prm))
    if kind == K_INFLATE:
        return dist_inflate(x, prm[0], data, start)
    if kind == K_REVOLVE:
        return dist_revolve(x, data, start)
    return dist_sweep(x, data, start)


@wp.func
def falloff(x: float):
    """Wyvill falloff g(x) and its derivative."""
    if x <= 0.0:
        return wp.vec2(1.0, 0.0)
    if x >= 1.0:
        return wp.vec2(0.0, 0.0)
    t = 1.0 - x * x
    return wp.vec2(t * t * t, -6.0 * x * t * t)


@wp.func
def evaluate_primitive(m: ModelArrays, node: int, q: wp.vec3):
    """(F, dF/dq, colour) of primitive ``node`` at ``q`` (parent frame)."""
    r = m.ref[node]
    inv = m.inverse[r]
    x = apply_inverse(inv, q)
    dg = primitive_distance(m.kind[node], x, m.params[node], m.data, m.data_start[r])
    rad = m.radius[r]
    fg = falloff(dg[0] / rad)
    out = vec7()
    if fg[0] > 0.0:
        g = pull_gradient(inv, (fg[1] / rad) * wp.vec3(dg[1], dg[2], dg[3]))
        c = m.color[r]
        out = vec7(fg[0], g[0], g[1], g[2], c[0], c[1], c[2], 0.0)
    return out


@wp.func
def primitive_value(m: ModelArrays, node: int, q: wp.vec3):
    """F of primitive ``node`` at ``q`` alone (the rest of the vec7 is 0)."""
    r = m.ref[node]
    x = apply_inverse(m.inverse[r], q)
    d = primitive_distance(m.kind[node], x, m.params[node], m.data, m.data_start[r])[0]
    return vec7(falloff(d / m.radius[r])[0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


# --------------------------------------------------------------------------
# warps: point forward into the child's frame, gradient back


@wp.func
def rotate_about(v: wp.vec3, a: wp.vec3, angle: float):
    c = wp.cos(angle)
    s = wp.sin(angle)
    return v * c + wp.cross(a, v) * s + a * (wp.dot(a, v) * (1.0 - c))


@wp.func
def bend_up(m: ModelArrays, node: int):
    st = m.data_start[m.ref[node]]
    return wp.vec3(m.data[st], m.data[st + 1], m.data[st + 2])


@wp.func
def warp_forward(m: ModelArrays, node: int, p: wp.vec3):
    x = apply_inverse(m.inverse[m.ref[node]], p)
    prm = m.params[node]
    a = wp.vec3(prm[0], prm[1], prm[2])
    kind = m.kind[node]
    if kind == K_TWIST:
        return rotate_about(x, a, -prm[3] * wp.dot(a, x))
    if kind == K_TAPER:
        t = wp.dot(a, x)
        s = 1.0 / wp.max(1.0 + prm[3] * t, 0.05)
        return s * x + (t * (1.0 - s)) * a
    u = bend_up(m, node)
    w = wp.cross(a, u)
    rho = prm[3]
    bx = wp.dot(x, a)
    by = rho - wp.dot(x, u)
    r = wp.max(wp.sqrt(bx * bx + by * by), 1.0e-12)
    return (rho * wp.atan2(bx, by)) * a + (rho - r) * u + wp.dot(x, w) * w


@wp.func
def warp_gradient(m: ModelArrays, node: int, p: wp.vec3, g: wp.vec3):
    """Gradient in the warp's parent frame from the child's gradient ``g``: (J W A)^T g."""
    inv = m.inverse[m.ref[node]]
    x = apply_inverse(inv, p)
    prm = m.params[node]
    a = wp.vec3(prm[0], prm[1], prm[2])
    kind = m.kind[node]
    out = wp.vec3(0.0)
    if kind == K_TWIST:
        angle = -prm[3] * wp.dot(a, x)
        q = rotate_about(x, a, angle)
        out = rotate_about(g, a, -angle) - (prm[3] * wp.dot(wp.cross(a, q), g)) * a
    elif kind == K_TAPER:
        t = wp.dot(a, x)
        scale = 1.0 + prm[3] * t
        if scale >= 0.05:
            s = 1.0 / scale
            perp = x - t * a
            out = s * g + (-prm[3] * s * s * wp.dot(perp, g) + (1.0 - s) * wp.dot(a, g)) * a
        else:
            out = 0.05 * g
    else:
        u = bend_up(m, node)
        w = wp.cross(a, u)
        rho = prm[3]
        bx = wp.dot(x, a)
        by = rho - wp.dot(x, u)
        r2 = wp.max(bx * bx + by * by, 1.0e-24)
        r = wp.sqrt(r2)
        gd = wp.dot(g, a)
        gu = wp.dot(g, u)
        out = (gd * rho / r2) * (by * a + bx * u) + (gu / r) * (-bx * a + by * u) + wp.dot(g, w) * w
    return pull_gradient(inv, out)


# --------------------------------------------------------------------------
# operators on (value, gradient, colour) accumulators


@wp.func
def combine_kind(kind: int, p0: float, acc: vec7, r: vec7, first: bool):
    """Fold result ``r`` into accumulator ``acc`` (``first``: ``r`` starts it).

    ``p0`` is the operator's first parameter: ``k`` of a smooth blend, the
    "operands stored as (b, a)" flag of a difference."""
    k = p0
    reverse = p0
    if kind == K_BLEND or kind == K_SMOOTH:
        w = r[0]
        gw = float(1.0)
        if kind == K_SMOOTH:
            # accumulate S = sum F^k and sum F^(k-1) grad F; then grad (S^(1/k)) = S^(1/k - 1) sum F^(k-1) grad F
            w = wp.pow(r[0], k)
            gw = wp.pow(r[0], k - 1.0)
        lifted = vec7(w, gw * r[1], gw * r[2], gw * r[3], w * r[4], w * r[5], w * r[6], 0.0)
        if first:
            return lifted
        return acc + lifted
    if first:
        return r
    if kind == K_UNION:
        if r[0] > acc[0]:
            return r
        return acc
    if kind == K_INTERSECTION:
        if r[0] < acc[0]:
            return r
        return acc
    # difference: min(F_a, 1 - min(F_b, 1)); operands were evaluated as (a, b) or (b, a)
    a = acc
    b = r
    if reverse > 0.5:
        a = r
        b = acc
    t = 1.0 - wp.min(b[0], 1.0)
    if a[0] <= t:
        return a
    if b[0] <= 0.0:
        # F_a > 1 clamped by the empty b: constant 1, still a's colour
        return vec7(t, 0.0, 0.0, 0.0, a[4], a[5], a[6], 0.0)
    if b[0] >= 1.0:
        return vec7(t, 0.0, 0.0, 0.0, b[4], b[5], b[6], 0.0)
    return vec7(t, -b[1], -b[2], -b[3], b[4], b[5], b[6], 0.0)


@wp.func
def finalize_kind(kind: int, k: float, acc: vec7):
    out = acc
    if kind == K_BLEND or kind == K_SMOOTH:
        if acc[0] > 0.0:
            # divide (not multiply by 1/S): S = sum F^k can be denormal, 1/S would overflow
            s = acc[0]
            out = vec7(s, acc[1], acc[2], acc[3], acc[4] / s, acc[5] / s, acc[6] / s, 0.0)
            if kind == K_SMOOTH:
                v = wp.pow(s, 1.0 / k)
                out = vec7(v, v * acc[1] / s, v * acc[2] / s, v * acc[3] / s, out[4], out[5], out[6], 0.0)
    if out[0] <= 0.0:
        out = vec7()
    return out


# --------------------------------------------------------------------------
# interval mode: bounds of F over a ball (centre, radius), for empty-space rejection


@wp.func
def ball_meets_box(c: wp.vec3, rad: float, lo: wp.vec3, hi: wp.vec3):
    return (
        c[0] + rad >= lo[0] and c[0] - rad <= hi[0] and c[1] + rad >= lo[1] and c[1] - rad <= hi[1]
        and c[2] + rad >= lo[2] and c[2] - rad <= hi[2]
    )  # fmt: skip


@wp.func
def convex_skeleton(kind: int):
    """Whether a primitive's skeleton is convex (its distance a convex function):
    point, segment, disc, solid cone and box; not a ring, a polygon (which
    may be concave) or the sketched primitives."""
    return kind == K_POINT or kind == K_SEGMENT or kind == K_DISC or kind == K_CONE or kind == K_BOX


@wp.func
def interval_primitive(m: ModelArrays, node: int, c: wp.vec3, rad: float, half: float):
    """(F_min, F_max) of primitive ``node`` over the ball of radius ``rad``
    around ``c``, or, when ``half`` > 0, over the axis-aligned cube of half
    side ``half`` that the ball circumscribes (``rad = sqrt(3) half``).

    Distances to a solid skeleton are 1-Lipschitz, so d varies by at most the
    ball's radius in the local frame (``rad`` times the stretch of the inverse
    map). For a cube and a convex skeleton (point, segment, disc, cone, box)
    the distance is also a convex function, so it lies above its tangent plane
    at the centre: ``d(c + e) >= d(c) + (A^T grad d) . e >= d(c) - half |A^T
    grad d|_1`` for ``|e_i| <= half`` (A the inverse map's linear part). That
    bound is never looser than the ball's (``|v|_1 <= sqrt(3) |v|_2``) and is
    much tighter where the surface is parallel to the grid's planes."""
    kind = m.kind[node]
    if kind >= K_INFLATE:
        # spline-based distances have no global Lipschitz bound: F is in [0, 1]
        return vec7(0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    r = m.ref[node]
    inv = m.inverse[r]
    x = apply_inverse(inv, c)
    dg = primitive_distance(kind, x, m.params[node], m.data, m.data_start[r])
    d = dg[0]
    slack = rad * m.stretch[r]
    near = wp.max(d - slack, 0.0)
    if half > 0.0 and d > 0.0 and convex_skeleton(kind):
        a = pull_gradient(inv, wp.vec3(dg[1], dg[2], dg[3]))
        near = wp.max(near, d - half * (wp.abs(a[0]) + wp.abs(a[1]) + wp.abs(a[2])))
    rr = m.radius[r]
    return vec7(falloff((d + slack) / rr)[0], falloff(near / rr)[0], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@wp.func
def combine_interval(kind: int, p0: float, acc: vec7, r: vec7, first: bool):
    """Interval counterpart of :func:`combine_kind`; every operator is monotone in each operand."""
    k = p0
    reverse = p0
    lo = r[0]
    hi = r[1]
    if kind == K_SMOOTH:
        lo = wp.pow(lo, k)
        hi = wp.pow(hi, k)
    if first:
        return vec7(lo, hi, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if kind == K_BLEND or kind == K_SMOOTH:
        return vec7(acc[0] + lo, acc[1] + hi, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if kind == K_UNION:
        return vec7(wp.max(acc[0], lo), wp.max(acc[1], hi), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    if kind == K_INTERSECTION:
        return vec7(wp.min(acc[0], lo), wp.min(acc[1], hi), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    a = acc
    b = r
    if reverse > 0.5:
        a = r
        b = acc
    return vec7(
        wp.min(a[0], 1.0 - wp.min(b[1], 1.0)), wp.min(a[1], 1.0 - wp.min(b[0], 1.0)), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    )


@wp.func
def finalize_interval(kind: int, k: float, acc: vec7):
    if kind == K_SMOOTH:
        return vec7(wp.pow(acc[0], 1.0 / k), wp.pow(acc[1], 1.0 / k), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    return acc


@wp.func
def grid_cell_of(m: ModelArrays, gi: int, x: wp.vec3):
    """Cell coordinates of ``x`` in grid ``gi`` (clamped into the grid)."""
    c = wp.cw_mul(x - m.grid_lower[gi], m.grid_inv_cell[gi])
    dims = m.grid_dims[gi]
    return wp.vec3i(
        wp.clamp(int(wp.floor(c[0])), 0, dims[0] - 1),
        wp.clamp(int(wp.floor(c[1])), 0, dims[1] - 1),
        wp.clamp(int(wp.floor(c[2])), 0, dims[2] - 1),
    )


@wp.func
def cell_operands(m: ModelArrays, gi: int, q: wp.vec3):
    """Range [first, end) in ``cell_items`` of the operands listed in the cell
    of wide-operator grid ``gi`` that holds ``q``."""
    cc = grid_cell_of(m, gi, q)
    dims = m.grid_dims[gi]
    cidx = m.grid_base[gi] + (cc[2] * dims[1] + cc[1]) * dims[0] + cc[0]
    return wp.vec2i(m.cell_offsets[cidx], m.cell_offsets[cidx + 1])


@wp.func
def next_ball_operand(m: ModelArrays, gi: int, q: wp.vec3, radius: float, cell: int, item: int):
    """Next (cell, item, operand) of a wide operator for the ball (q, radius).

    Walks the grid cells the ball's box overlaps (x fastest) and their items
    from ``(cell, item)`` on; an operand listed in several of those cells is
    returned only in the first of them (the componentwise max of the ball's
    first cell and the operand's first cell), so sums count it once.
    ``cell`` is a linear index within the grid; operand -1 when done.
    """
    dims = m.grid_dims[gi]
    c0 = grid_cell_of(m, gi, q - wp.vec3(radius))
    c1 = grid_cell_of(m, gi, q + wp.vec3(radius))
    base = m.grid_base[gi]
    cx = cell % dims[0]
    cy = (cell // dims[0]) % dims[1]
    cz = cell // (dims[0] * dims[1])
    it = item
    while cz <= c1[2]:
        lin = (cz * dims[1] + cy) * dims[0] + cx
        stop = m.cell_offsets[base + lin + 1]
        if it < 0:
            it = m.cell_offsets[base + lin]
        while it < stop:
            child = m.cell_items[it]
            first = grid_cell_of(m, gi, m.lower[child])
            if wp.max(first[0], c0[0]) == cx and wp.max(first[1], c0[1]) == cy and wp.max(first[2], c0[2]) == cz:
                return wp.vec3i(lin, it + 1, child)
            it += 1
        it = -1
        cx += 1
        if cx > c1[0]:
            cx = c0[0]
            cy += 1
            if cy > c1[1]:
                cy = c0[1]
                cz += 1
    return wp.vec3i(0, 0, -1)


@wp.func
def ball_cell_count(m: ModelArrays, gi: int, q: wp.vec3, radius: float):
    """Number of cells of grid ``gi`` that the ball's box overlaps."""
    c0 = grid_cell_of(m, gi, q - wp.vec3(radius))
    c1 = grid_cell_of(m, gi, q + wp.vec3(radius))
    return (c1[0] - c0[0] + 1) * (c1[1] - c0[1] + 1) * (c1[2] - c0[2] + 1)



# --------------------------------------------------------------------------
# array mode: one traversal evaluates a whole block of grid points


#: half side of a 2-cell sub-block's cube in cells, plus 1e-4 (its ball has sqrt(3) times that radius)
SUB_HALF = 1.0001
_SUB_HALF = wp.constant(SUB_HALF)
#: ball radius of a 2-cell sub-block in cells: its half diagonal sqrt(3), plus 1e-4
SUB_BALL = 1.7320509 * SUB_HALF
_SUB_BALL = wp.constant(SUB_BALL)


@wp.struct
class BlockRows:
    """Scratch of one array-mode traversal: the F values of a block of
    ``BLOCK_POINTS`` grid points (8^3, x fastest) held per register slot.

    ``rows[base + s * BLOCK_POINTS + j]`` is slot ``s`` at point ``j``; slot
    ``result`` holds a primitive's values over its index range only, slot
    ``result + 1`` is 1.0 where the point is wanted (others are skipped).
    Point ``(i, j, k)`` is at ``origin + h * (corner + (i, j, k))``, computed
    as :func:`grid_point` does so that it is bit-identical to the grid's.
    Bounds rows bound F over the cube of half side ``half`` (and the ball of
    radius ``ball``), in units of ``h``, around each 2-cell sub-block's
    centre (:data:`SUB_HALF` and :data:`SUB_BALL` unless a caller widens
    them)."""

    rows: wp.array(dtype=wp.float32)
    base: int
    result: int
    origin: wp.vec3
    h: float
    corner: wp.vec3i
    half: float
    ball: float


BLOCK_SIDE = 8
BLOCK_POINTS = BLOCK_SIDE * BLOCK_SIDE * BLOCK_SIDE
_BSIDE = wp.constant(BLOCK_SIDE)
_BPOINTS = wp.constant(BLOCK_POINTS)


@wp.func
def block_rows(rows: wp.array(dtype=wp.float32), t: int, result: int, origin: wp.vec3, h: float, corner: wp.vec3i):
    """The :class:`BlockRows` of the ``t``-th block of a launch (its rows at
    ``t * (result + 2) * BLOCK_POINTS``), first point at grid index ``corner``."""
    ctx = BlockRows()
    ctx.rows = rows
    ctx.base = t * (result + 2) * _BPOINTS
    ctx.result = result
    ctx.origin = origin
    ctx.h = h
    ctx.corner = corner
    ctx.half = _SUB_HALF
    ctx.ball = _SUB_BALL
    return ctx


@wp.func
def block_result(ctx: BlockRows, r: vec7, l: int):
    """F at block point ``l`` from a finished array-mode walk's result ``r``."""
    if in_range(r, l % _BSIDE, (l // _BSIDE) % _BSIDE, l // (_BSIDE * _BSIDE)):
        return ctx.rows[ctx.base + int(r[6]) * _BPOINTS + l]
    return 0.0


@wp.func
def grid_point(origin: wp.vec3, h: float, gx: int, gy: int, gz: int):
    """Position of grid vertex (gx, gy, gz): ``origin + h * (gx, gy, gz)``."""
    return origin + h * wp.vec3(float(gx), float(gy), float(gz))


@wp.func
def points_cube(origin: wp.vec3, h: float, corner: wp.vec3i):
    """(centre, half side, grown by 1e-4) of the cube spanned by the block of grid points from index
    ``corner``: what an array-mode walk of the block prunes by."""
    lo = grid_point(origin, h, corner[0], corner[1], corner[2])
    hi = grid_point(origin, h, corner[0] + _BSIDE - 1, corner[1] + _BSIDE - 1, corner[2] + _BSIDE - 1)
    half = 0.5 * wp.max(wp.max(hi[0] - lo[0], hi[1] - lo[1]), hi[2] - lo[2])
    return 0.5 * (lo + hi), half * 1.0001


@wp.func
def block_center(ctx: BlockRows):
    """(centre, half side) of the cube spanned by the block's points."""
    return points_cube(ctx.origin, ctx.h, ctx.corner)


@wp.func
def index_range(ctx: BlockRows, lo: wp.vec3, hi: wp.vec3):
    """Local index range (i0, j0, k0, i1, j1, k1, 0, 0) of the block points in
    the box [lo, hi]. The range reaches 1e-3 cells past the box, far more than
    float32 rounding of a point's position, so a point inside the box is never
    left out (those just outside are evaluated for nothing: F = 0 there)."""
    a = (lo - ctx.origin) / ctx.h
    b = (hi - ctx.origin) / ctx.h
    return vec7(
        float(wp.max(int(wp.ceil(a[0] - 1.0e-3)) - ctx.corner[0], 0)),
        float(wp.max(int(wp.ceil(a[1] - 1.0e-3)) - ctx.corner[1], 0)),
        float(wp.max(int(wp.ceil(a[2] - 1.0e-3)) - ctx.corner[2], 0)),
        float(wp.min(int(wp.floor(b[0] + 1.0e-3)) - ctx.corner[0], _BSIDE - 1)),
        float(wp.min(int(wp.floor(b[1] + 1.0e-3)) - ctx.corner[1], _BSIDE - 1)),
        float(wp.min(int(wp.floor(b[2] + 1.0e-3)) - ctx.corner[2], _BSIDE - 1)),
        0.0,
        0.0,
    )


@wp.func
def empty_range(row: int):
    return vec7(float(_BSIDE), float(_BSIDE), float(_BSIDE), -1.0, -1.0, -1.0, float(row), 0.0)


@wp.func
def in_range(rg: vec7, i: int, j: int, k: int):
    return (
        float(i) >= rg[0] and float(i) <= rg[3] and float(j) >= rg[1] and float(j) <= rg[4]
        and float(k) >= rg[2] and float(k) <= rg[5]
    )  # fmt: skip


@wp.func
def clear_row(ctx: BlockRows, row: int):
    start = ctx.base + row * _BPOINTS
    for j in range(_BPOINTS):
        ctx.rows[start + j] = 0.0


@wp.func
def fold_rows(kind: int, p0: float, acc: vec7, r: vec7, first: bool, ctx: BlockRows, sp: int):
    """Array-mode :func:`combine_kind`: fold the values of ``r`` (its index range
    and row in ``r[0:6]``, ``r[6]``) into slot ``sp`` (range ``acc``); returns
    the slot's new range. Points outside a range hold F = 0."""
    dst = ctx.base + sp * _BPOINTS
    src_row = int(r[6])
    src = ctx.base + src_row * _BPOINTS
    k = p0
    smooth = kind == K_SMOOTH
    if first:
        if src_row != sp:
            clear_row(ctx, sp)
        for kk in range(int(r[2]), int(r[5]) + 1):
            for jj in range(int(r[1]), int(r[4]) + 1):
                for ii in range(int(r[0]), int(r[3]) + 1):
                    j = (kk * _BSIDE + jj) * _BSIDE + ii
                    v = ctx.rows[src + j]
                    if smooth:
                        v = wp.pow(v, k)
                    ctx.rows[dst + j] = v
        return vec7(r[0], r[1], r[2], r[3], r[4], r[5], float(sp), 0.0)
    if kind == K_BLEND or kind == K_SMOOTH or kind == K_UNION:
        for kk in range(int(r[2]), int(r[5]) + 1):
            for jj in range(int(r[1]), int(r[4]) + 1):
                for ii in range(int(r[0]), int(r[3]) + 1):
                    j = (kk * _BSIDE + jj) * _BSIDE + ii
                    v = ctx.rows[src + j]
                    if kind == K_UNION:
                        ctx.rows[dst + j] = wp.max(ctx.rows[dst + j], v)
                    elif smooth:
                        ctx.rows[dst + j] = ctx.rows[dst + j] + wp.pow(v, k)
                    else:
                        ctx.rows[dst + j] = ctx.rows[dst + j] + v
        return vec7(
            wp.min(acc[0], r[0]), wp.min(acc[1], r[1]), wp.min(acc[2], r[2]),
            wp.max(acc[3], r[3]), wp.max(acc[4], r[4]), wp.max(acc[5], r[5]), float(sp), 0.0,
        )  # fmt: skip
    # intersection and difference see every point (F = 0 outside a range matters)
    reverse = p0 > 0.5
    for j in range(_BPOINTS):
        ii = j % _BSIDE
        jj = (j // _BSIDE) % _BSIDE
        kk = j // (_BSIDE * _BSIDE)
        v = float(0.0)
        if in_range(r, ii, jj, kk):
            v = ctx.rows[src + j]
        w = ctx.rows[dst + j]
        if kind == K_INTERSECTION:
            ctx.rows[dst + j] = wp.min(w, v)
        else:
            a = w
            b = v
            if reverse:
                a = v
                b = w
            ctx.rows[dst + j] = wp.min(a, 1.0 - wp.min(b, 1.0))
    if kind == K_INTERSECTION:
        return vec7(
            wp.max(acc[0], r[0]), wp.max(acc[1], r[1]), wp.max(acc[2], r[2]),
            wp.min(acc[3], r[3]), wp.min(acc[4], r[4]), wp.min(acc[5], r[5]), float(sp), 0.0,
        )  # fmt: skip
    if reverse:
        return vec7(r[0], r[1], r[2], r[3], r[4], r[5], float(sp), 0.0)
    return acc


@wp.func
def finalize_rows(kind: int, k: float, acc: vec7, ctx: BlockRows, sp: int):
    """Array-mode :func:`finalize_kind`: a smooth blend's root S^(1/k) over its range."""
    if kind == K_SMOOTH:
        dst = ctx.base + sp * _BPOINTS
        for kk in range(int(acc[2]), int(acc[5]) + 1):
            for jj in range(int(acc[1]), int(acc[4]) + 1):
                for ii in range(int(acc[0]), int(acc[3]) + 1):
                    j = (kk * _BSIDE + jj) * _BSIDE + ii
                    v = ctx.rows[dst + j]
                    if v > 0.0:
                        ctx.rows[dst + j] = wp.pow(v, 1.0 / k)
    return vec7(acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], float(sp), 0.0)


# bounds rows: array mode for interval bounds over the 4^3 sub-blocks (2^3
# cells each) of an 8^3-cell block; entry j of a row is sub-block j's F_min,
# entry BOUND_SUBS + j its F_max (rows keep the BLOCK_POINTS stride)

SUB_BLOCK_SIDE = 4
SUB_BLOCKS = SUB_BLOCK_SIDE * SUB_BLOCK_SIDE * SUB_BLOCK_SIDE
_SSIDE = wp.constant(SUB_BLOCK_SIDE)
_SUBS = wp.constant(SUB_BLOCKS)


@wp.func
def sub_block_center(ctx: BlockRows, si: int, sj: int, sk: int):
    """Centre of sub-block (si, sj, sk) of the block whose first cell is at
    grid index ``ctx.corner``; its cube has half side ``ctx.h``."""
    return grid_point(ctx.origin, ctx.h, ctx.corner[0] + 2 * si + 1, ctx.corner[1] + 2 * sj + 1, ctx.corner[2] + 2 * sk + 1)


@wp.func
def sub_range(ctx: BlockRows, lo: wp.vec3, hi: wp.vec3):
    """Index range (i0, j0, k0, i1, j1, k1, 0, 0) of the sub-blocks whose cube
    meets the box [lo, hi], widened by 1e-3 cells: a sub-block left out
    provably sees F = 0 of that node."""
    a = (lo - ctx.origin) / ctx.h
    b = (hi - ctx.origin) / ctx.h
    r = vec7()
    for d in range(3):
        c = float(ctx.corner[d]) + 1.0
        r[d] = float(wp.max(int(wp.ceil(0.5 * (a[d] - ctx.half - c) - 1.0e-3)), 0))
        r[d + 3] = float(wp.min(int(wp.floor(0.5 * (b[d] + ctx.half - c) + 1.0e-3)), _SSIDE - 1))
    return r


@wp.func
def clear_bounds(ctx: BlockRows, row: int):
    start = ctx.base + row * _BPOINTS
    for j in range(2 * _SUBS):
        ctx.rows[start + j] = 0.0


@wp.func
def bounds_leaf(m: ModelArrays, node: int, ctx: BlockRows):
    """Bounds rows: (F_min, F_max) of primitive ``node`` over each sub-block
    cube in its range (:func:`interval_primitive`'s cube bound) into the
    result slot ([0, inf) for a warp, as interval mode); returns (range,
    result slot)."""
    rg = sub_range(ctx, m.lower[node], m.upper[node])
    res = ctx.base + ctx.result * _BPOINTS
    warped = m.kind[node] >= K_TWIST
    for kk in range(int(rg[2]), int(rg[5]) + 1):
        for jj in range(int(rg[1]), int(rg[4]) + 1):
            for ii in range(int(rg[0]), int(rg[3]) + 1):
                j = (kk * _SSIDE + jj) * _SSIDE + ii
                b = vec7(0.0, 1.0e30, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                if not warped:
                    b = interval_primitive(m, node, sub_block_center(ctx, ii, jj, kk), ctx.h * ctx.ball, ctx.h * ctx.half)
                ctx.rows[res + j] = b[0]
                ctx.rows[res + _SUBS + j] = b[1]
    return vec7(rg[0], rg[1], rg[2], rg[3], rg[4], rg[5], float(ctx.result), 0.0)


@wp.func
def bounds_at(ctx: BlockRows, row: int, j: int):
    at = ctx.base + row * _BPOINTS + j
    return vec7(ctx.rows[at], ctx.rows[at + _SUBS], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@wp.func
def set_bounds(ctx: BlockRows, row: int, j: int, b: vec7):
    at = ctx.base + row * _BPOINTS + j
    ctx.rows[at] = b[0]
    ctx.rows[at + _SUBS] = b[1]


@wp.func
def fold_bounds(kind: int, p0: float, acc: vec7, r: vec7, first: bool, ctx: BlockRows, sp: int):
    """Bounds-rows :func:`combine_interval`, with the range logic of
    :func:`fold_rows` (sub-blocks outside a range hold [0, 0])."""
    src_row = int(r[6])
    if first:
        if src_row != sp:
            clear_bounds(ctx, sp)
        for kk in range(int(r[2]), int(r[5]) + 1):
            for jj in range(int(r[1]), int(r[4]) + 1):
                for ii in range(int(r[0]), int(r[3]) + 1):
                    j = (kk * _SSIDE + jj) * _SSIDE + ii
                    set_bounds(ctx, sp, j, combine_interval(kind, p0, vec7(), bounds_at(ctx, src_row, j), True))
        return vec7(r[0], r[1], r[2], r[3], r[4], r[5], float(sp), 0.0)
    if kind == K_BLEND or kind == K_SMOOTH or kind == K_UNION:
        for kk in range(int(r[2]), int(r[5]) + 1):
            for jj in range(int(r[1]), int(r[4]) + 1):
                for ii in range(int(r[0]), int(r[3]) + 1):
                    j = (kk * _SSIDE + jj) * _SSIDE + ii
                    set_bounds(ctx, sp, j, combine_interval(kind, p0, bounds_at(ctx, sp, j), bounds_at(ctx, src_row, j), False))
        return vec7(
            wp.min(acc[0], r[0]), wp.min(acc[1], r[1]), wp.min(acc[2], r[2]),
            wp.max(acc[3], r[3]), wp.max(acc[4], r[4]), wp.max(acc[5], r[5]), float(sp), 0.0,
        )  # fmt: skip
    # intersection and difference see every sub-block ([0, 0] outside a range matters)
    for j in range(_SUBS):
        v = vec7()
        if in_range(r, j % _SSIDE, (j // _SSIDE) % _SSIDE, j // (_SSIDE * _SSIDE)):
            v = bounds_at(ctx, src_row, j)
        set_bounds(ctx, sp, j, combine_interval(kind, p0, bounds_at(ctx, sp, j), v, False))
    if kind == K_INTERSECTION:
        return vec7(
            wp.max(acc[0], r[0]), wp.max(acc[1], r[1]), wp.max(acc[2], r[2]),
            wp.min(acc[3], r[3]), wp.min(acc[4], r[4]), wp.min(acc[5], r[5]), float(sp), 0.0,
        )  # fmt: skip
    if p0 > 0.5:
        return vec7(r[0], r[1], r[2], r[3], r[4], r[5], float(sp), 0.0)
    return acc


@wp.func
def finalize_bounds(kind: int, k: float, acc: vec7, ctx: BlockRows, sp: int):
    """Bounds-rows :func:`finalize_interval`: a smooth blend's root over its range."""
    if kind == K_SMOOTH:
        for kk in range(int(acc[2]), int(acc[5]) + 1):
            for jj in range(int(acc[1]), int(acc[4]) + 1):
                for ii in range(int(acc[0]), int(acc[3]) + 1):
                    j = (kk * _SSIDE + jj) * _SSIDE + ii
                    set_bounds(ctx, sp, j, finalize_interval(kind, k, bounds_at(ctx, sp, j)))
    return vec7(acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], float(sp), 0.0)


@wp.func
def sub_bounds(ctx: BlockRows, r: vec7, j: int):
    """(F_min, F_max) of sub-block ``j`` from a finished bounds-rows walk's result ``r``."""
    if in_range(r, j % _SSIDE, (j // _SSIDE) % _SSIDE, j // (_SSIDE * _SSIDE)):
        return bounds_at(ctx, int(r[6]), j)
    return vec7()


def make_simple_rows(offset):
    """Array mode for a simple skeleton: F at every point of the range ``rg``
    of a block into row ``res``, branch-free so the compiler can vectorize the
    innermost loop (values at unwanted points are computed and never read);
    the same arithmetic as the general path, so the same values."""

    @wp.func
    def simple_rows(ctx: BlockRows, rg: vec7, res: int, inv: mat34, prm: wp.vec4, rad: float):
        for kk in range(int(rg[2]), int(rg[5]) + 1):
            for jj in range(int(rg[1]), int(rg[4]) + 1):
                row = res + (kk * _BSIDE + jj) * _BSIDE
                pz = ctx.origin[2] + ctx.h * float(ctx.corner[2] + kk)
                py = ctx.origin[1] + ctx.h * float(ctx.corner[1] + jj)
                for ii in range(int(rg[0]), int(rg[3]) + 1):
                    px = ctx.origin[0] + ctx.h * float(ctx.corner[0] + ii)
                    t = wp.length(offset(apply_inverse(inv, wp.vec3(px, py, pz)), prm)) / rad
                    u = wp.max(1.0 - t * t, 0.0)
                    ctx.rows[row + ii] = wp.where(t < 1.0, u * u * u, 0.0)

    return simple_rows


point_rows = make_simple_rows(point_offset)
segment_rows = make_simple_rows(segment_offset)
box_rows = make_simple_rows(box_offset)
cone_rows = make_simple_rows(cone_offset)


def make_walks_grid(spatial: bool):
    """``walks_grid(m, node, q, radius)``: whether operator ``node`` visits its
    operands through its grid, in point mode (``spatial`` False) or over a
    ball or block (``spatial`` True)."""

    @wp.func
    def walks_grid(m: ModelArrays, node: int, q: wp.vec3, radius: float):
        """Whether operator ``node`` visits its operands through its grid: always
        for a point; for a ball only while it overlaps fewer cells than the
        operator has operands (``params[1]``), else a plain scan is cheaper."""
        gi = m.ref[node]
        if gi < 0:
            return False
        if wp.static(spatial):
            return float(ball_cell_count(m, gi, q, radius)) < m.params[node][1]
        return True

    return walks_grid


def make_flat_operator(prune: bool, derivatives: bool):
    """Point mode's fold of a flat operator (one whose operands are all primitives):
    ``flat_operator(m, node, q) -> vec7``."""

    @wp.func(inline=True)
    def flat_operand(m: ModelArrays, node: int, q: wp.vec3):
        """Point mode: primitive ``node`` at ``q`` (0 outside its box when pruning)."""
        if wp.static(prune):
            if not inside_box(q, m.lower[node], m.upper[node]):
                return vec7()
        if wp.static(derivatives):
            return evaluate_primitive(m, node, q)
        return primitive_value(m, node, q)

    @wp.func(inline=True)
    def flat_operator(m: ModelArrays, node: int, q: wp.vec3):
        """Point mode: an operator whose operands are all primitives, folded in
        one loop instead of a descent and an ascent per operand; the same
        operands in the same order through :func:`combine_kind` as the general
        walk, so the result is bit-identical."""
        kind = m.kind[node]
        p0 = m.params[node][0]
        acc = vec7()
        gi = m.ref[node]
        if wp.static(prune) and gi >= 0:
            # wide: the operands listed in q's grid cell, the accumulator starting at 0
            cells = cell_operands(m, gi, q)
            if cells[0] == cells[1]:
                return vec7()
            for c in range(cells[0], cells[1]):
                acc = combine_kind(kind, p0, acc, flat_operand(m, m.cell_items[c], q), False)
            return finalize_kind(kind, p0, acc)
        c = node + 1
        end = m.skip[node]
        while c < end:
            acc = combine_kind(kind, p0, acc, flat_operand(m, c, q), c == node + 1)
            # an intersection that reached 0 stays 0 (every field is >= 0)
            if wp.static(prune) and kind == K_INTERSECTION and acc[0] <= 0.0:
                break
            c = m.skip[c]
        return finalize_kind(kind, p0, acc)

    return flat_operator


def make_get_slot(ball: bool, array: bool, full: bool):
    """``get_slot(sv, sh, sg, sc, sp) -> vec7``: register ``sp`` of a traversal in
    the layout its mode folds: (F_min, F_max) for a ball, an index range for
    array mode, (F, grad F, colour) with ``full`` derivatives, else F."""

    @wp.func
    def get_slot(sv: vec_slots, sh: vec_slots, sg: mat_slots3, sc: mat_slots3, sp: int):
        if wp.static(ball):
            return vec7(sv[sp], sh[sp], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if wp.static(array):
            lo = sg[sp]
            hi = sc[sp]
            return vec7(lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], float(sp), 0.0)
        if wp.static(not full):
            return vec7(sv[sp], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        g = sg[sp]
        c = sc[sp]
        return vec7(sv[sp], g[0], g[1], g[2], c[0], c[1], c[2], 0.0)

    return get_slot


def make_rows_leaf(point):
    """Array mode's leaf: ``rows_leaf(m, node, ctx)`` writes F of primitive or
    warp ``node`` at the block's points; ``point`` is the point-mode walk
    (``make_evaluate(..., _core=True)``) that evaluates a warp's subtree at
    each point."""

    @wp.func
    def rows_leaf(m: ModelArrays, node: int, ctx: BlockRows):
        """Array mode: F of primitive or warp ``node`` at the wanted block points
        in its box, into the result slot; returns (range, result slot)."""
        rg = index_range(ctx, m.lower[node], m.upper[node])
        res = ctx.base + ctx.result * _BPOINTS
        want = res + _BPOINTS
        kind = m.kind[node]
        leaf = kind < K_PRIM_END
        r = m.ref[node]
        inv = m.inverse[r]
        prm = m.params[node]
        start = m.data_start[r]
        rad = m.radius[r]
        simple = True
        if kind == K_POINT:
            point_rows(ctx, rg, res, inv, prm, rad)
        elif kind == K_SEGMENT:
            segment_rows(ctx, rg, res, inv, prm, rad)
        elif kind == K_BOX:
            box_rows(ctx, rg, res, inv, prm, rad)
        elif kind == K_CONE:
            cone_rows(ctx, rg, res, inv, prm, rad)
        else:
            simple = False
        if simple:
            return vec7(rg[0], rg[1], rg[2], rg[3], rg[4], rg[5], float(ctx.result), 0.0)
        for kk in range(int(rg[2]), int(rg[5]) + 1):
            for jj in range(int(rg[1]), int(rg[4]) + 1):
                for ii in range(int(rg[0]), int(rg[3]) + 1):
                    j = (kk * _BSIDE + jj) * _BSIDE + ii
                    if ctx.rows[want + j] != 0.0:
                        p = grid_point(ctx.origin, ctx.h, ctx.corner[0] + ii, ctx.corner[1] + jj, ctx.corner[2] + kk)
                        v = float(0.0)
                        if leaf:
                            x = apply_inverse(inv, p)
                            v = falloff(primitive_distance(kind, x, prm, m.data, start)[0] / rad)[0]
                        else:
                            v = point(m, p, 0.0, node, ctx)[0]
                        ctx.rows[res + j] = v
        return vec7(rg[0], rg[1], rg[2], rg[3], rg[4], rg[5], float(ctx.result), 0.0)

    return rows_leaf


def make_leaf(interval: bool, derivatives: bool, array: bool, cube: bool):
    """The leaf evaluator of one traversal mode, ``leaf(m, node, kind, q, radius,
    ctx) -> vec7``: for a primitive and, in interval and array modes (which do
    not descend into warps), for a warp. Bounds rows (``interval`` and
    ``array``), array-mode rows, interval bounds over the ball (or ``cube``),
    or the point value with or without ``derivatives``."""
    if interval and array:

        @wp.func(inline=True)
        def leaf(m: ModelArrays, node: int, kind: int, q: wp.vec3, radius: float, ctx: BlockRows):
            return bounds_leaf(m, node, ctx)

    elif array:
        # a warp's subtree is evaluated point by point with the plain walk
        rows_leaf = make_rows_leaf(make_evaluate(True, derivatives=False, _core=True))

        @wp.func(inline=True)
        def leaf(m: ModelArrays, node: int, kind: int, q: wp.vec3, radius: float, ctx: BlockRows):
            return rows_leaf(m, node, ctx)

    elif interval:

        @wp.func(inline=True)
        def leaf(m: ModelArrays, node: int, kind: int, q: wp.vec3, radius: float, ctx: BlockRows):
            if kind >= K_TWIST:
                return vec7(0.0, 1.0e30, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            if wp.static(cube):
                return interval_primitive(m, node, q, radius * 1.7320509, radius)
            else:
                return interval_primitive(m, node, q, radius, 0.0)

    else:

        @wp.func(inline=True)
        def leaf(m: ModelArrays, node: int, kind: int, q: wp.vec3, radius: float, ctx: BlockRows):
            if wp.static(derivatives):
                return evaluate_primitive(m, node, q)
            else:
                return primitive_value(m, node, q)

    return leaf


def make_fold(interval: bool, array: bool):
    """The operator fold of one traversal mode, ``(fold, finish)``:
    ``fold(kind, p0, acc, r, first, ctx, sp)`` takes operand result ``r`` into
    accumulator ``acc`` (register ``sp``) and ``finish(kind, p0, acc, ctx,
    sp)`` closes the operator, with the formulas of bounds rows, array rows,
    interval or point mode."""
    if interval and array:
        return fold_bounds, finalize_bounds
    if array:
        return fold_rows, finalize_rows
    combine, finalize = (combine_interval, finalize_interval) if interval else (combine_kind, finalize_kind)

    # interval and point mode keep their registers in the walk, not in block rows

    @wp.func(inline=True)
    def fold(kind: int, p0: float, acc: vec7, r: vec7, first: bool, ctx: BlockRows, sp: int):
        return combine(kind, p0, acc, r, first)

    @wp.func(inline=True)
    def finish(kind: int, p0: float, acc: vec7, ctx: BlockRows, sp: int):
        return finalize(kind, p0, acc)

    return fold, finish


def make_evaluate(
    prune: bool, interval: bool = False, derivatives: bool = True, array: bool = False, cube: bool = False,
    count: bool = False, _core: bool = False,
):  # fmt: skip
    """The traversal as a Warp function ``evaluate(m, p, radius) -> vec7``.

    Point mode (``interval`` False) returns (F, grad F, colour) at ``p``
    (F alone, the rest 0, when ``derivatives`` is False; F is bit-identical
    either way); ``radius`` is ignored. Interval mode returns (F_min, F_max, 0...) over the
    ball of ``radius`` around ``p``: it always prunes (by ball-box overlap),
    treats a warp whose box meets the ball as unknown ([0, inf)), and visits
    the operands of a wide operator listed in the grid cells the ball overlaps.
    With ``cube`` too, ``radius`` is the half side of an axis-aligned cube and
    the bounds hold over the cube (:func:`interval_primitive`'s cube bound, as
    the bounds rows of array mode compute them).

    With ``count`` (interval and array modes) the result's last component
    (``r[7]``, otherwise 0) is the number of leaves the walk reached:
    primitives, and warps taken whole, whose boxes meet the ball, cube or
    block (and their ancestors' boxes too), the tape pruned over it. The
    count rides in a register row of its own (``sn``).

    The walk below is one generated body; what differs between the modes
    lives in the pieces it calls: :func:`make_leaf`, :func:`make_fold`,
    :func:`make_get_slot`, :func:`make_walks_grid`, :func:`make_flat_operator`.
    """
    if count and not (interval or array):
        raise ValueError("make_evaluate: count needs interval or array mode")
    use_grid = prune
    # array mode walks the tree once per block, pruning like interval mode over
    # the block's cube; warps inside it are evaluated point by point. With
    # ``interval`` too it bounds F over the block's 64 sub-blocks (bounds rows).
    spatial = interval or array
    bounds = interval and array
    ball = interval and not array
    full = derivatives and not interval and not array
    leaf = make_leaf(interval, derivatives, array, cube)
    fold, finish = make_fold(interval, array)
    get_slot = make_get_slot(ball, array, full)
    walks_grid = make_walks_grid(spatial)
    flat_operator = make_flat_operator(prune, derivatives)

    @wp.func(inline=True)
    def traverse(m: ModelArrays, p: wp.vec3, radius: float, root: int, ctx: BlockRows):
        sv = vec_slots()
        sh = vec_slots()
        sg = mat_slots3()
        sc = mat_slots3()
        sn = vec_slots()  # leaves reached, per register (``count``)
        cursor = ivec_slots()
        stop = ivec_slots()
        saved = mat_warps3()
        sp = int(-1)
        wsp = int(-1)
        q = p
        i = root
        r = vec7()
        descending = bool(True)
        while True:
            if descending:
                kind = m.kind[i]
                outside = bool(False)
                if wp.static(spatial):
                    outside = not ball_meets_box(q, radius, m.lower[i], m.upper[i])
                elif wp.static(prune):
                    outside = not inside_box(q, m.lower[i], m.upper[i])
                if outside:
                    r = vec7()
                    if wp.static(array):
                        r = empty_range(ctx.result)
                    descending = False
                elif kind < K_PRIM_END:
                    r = leaf(m, i, kind, q, radius, ctx)
                    if wp.static(count):
                        r[7] = 1.0
                    descending = False
                elif kind >= K_TWIST:
                    if wp.static(spatial):
                        # interval and array modes take a warp's subtree as one leaf
                        r = leaf(m, i, kind, q, radius, ctx)
                        if wp.static(count):
                            r[7] = 1.0
                        descending = False
                    else:
                        wsp += 1
                        saved[wsp] = q
                        q = warp_forward(m, i, q)
                        i = i + 1
                elif wp.static(not spatial) and m.params[i][2] > 0.5:
                    r = flat_operator(m, i, q)
                    descending = False
                elif wp.static(use_grid) and walks_grid(m, i, q, radius):
                    # wide sparse operator: visit the operands listed in the grid
                    # cell of q (point mode) or the cells the ball overlaps (interval)
                    gi = m.ref[i]
                    first_op = wp.vec3i(0, 0, -1)
                    if wp.static(spatial):
                        c0 = grid_cell_of(m, gi, q - wp.vec3(radius))
                        dims = m.grid_dims[gi]
                        first_op = next_ball_operand(m, gi, q, radius, (c0[2] * dims[1] + c0[1]) * dims[0] + c0[0], -1)
                    else:
                        cells = cell_operands(m, gi, q)
                        if cells[0] < cells[1]:
                            first_op = wp.vec3i(cells[1], cells[0] + 1, m.cell_items[cells[0]])
                    if first_op[2] >= 0:
                        sp += 1
                        sv[sp] = 0.0
                        if wp.static(ball):
                            sh[sp] = 0.0
                        if wp.static(count):
                            sn[sp] = 0.0
                        if wp.static(array):
                            if wp.static(bounds):
                                clear_bounds(ctx, sp)
                            else:
                                clear_row(ctx, sp)
                            e = empty_range(sp)
                            sg[sp] = wp.vec3(e[0], e[1], e[2])
                            sc[sp] = wp.vec3(e[3], e[4], e[5])
                        if wp.static(full):
                            sg[sp] = wp.vec3(0.0)
                            sc[sp] = wp.vec3(0.0)
                        stop[sp] = first_op[0]
                        cursor[sp] = first_op[1]
                        i = first_op[2]
                    else:
                        r = vec7()
                        if wp.static(array):
                            r = empty_range(ctx.result)
                        descending = False
                else:
                    i = i + 1
            else:
                if i == root:
                    break
                par = m.parent[i]
                pk = m.kind[par]
                if pk >= K_TWIST:
                    g = warp_gradient(m, par, saved[wsp], wp.vec3(r[1], r[2], r[3]))
                    r = vec7(r[0], g[0], g[1], g[2], r[4], r[5], r[6], 0.0)
                    q = saved[wsp]
                    wsp -= 1
                    i = par
                else:
                    prm = m.params[par]
                    wide = bool(False)
                    if wp.static(use_grid):
                        wide = walks_grid(m, par, q, radius)
                    first = i == par + 1 and not wide
                    if first:
                        sp += 1
                    if wp.static(count):
                        if first:
                            sn[sp] = r[7]
                        else:
                            sn[sp] = sn[sp] + r[7]
                    acc = fold(pk, prm[0], get_slot(sv, sh, sg, sc, sp), r, first, ctx, sp)
                    sv[sp] = acc[0]
                    if wp.static(ball):
                        sh[sp] = acc[1]
                    if wp.static(array):
                        sg[sp] = wp.vec3(acc[0], acc[1], acc[2])
                        sc[sp] = wp.vec3(acc[3], acc[4], acc[5])
                    if wp.static(full):
                        sg[sp] = wp.vec3(acc[1], acc[2], acc[3])
                        sc[sp] = wp.vec3(acc[4], acc[5], acc[6])
                    nxt = int(-1)
                    if wide:
                        if wp.static(spatial):
                            step = next_ball_operand(m, m.ref[par], q, radius, stop[sp], cursor[sp])
                            if step[2] >= 0:
                                stop[sp] = step[0]
                                cursor[sp] = step[1]
                                nxt = step[2]
                        elif cursor[sp] < stop[sp]:
                            nxt = m.cell_items[cursor[sp]]
                            cursor[sp] += 1
                    else:
                        nxt = m.skip[i]
                        if nxt >= m.skip[par]:
                            nxt = -1
                        # an intersection that reached 0 stays 0 (every field is >= 0)
                        if wp.static(prune) and pk == K_INTERSECTION:
                            if wp.static(ball):
                                if acc[1] <= 0.0:
                                    nxt = -1
                            elif wp.static(array):
                                if acc[3] < acc[0] or acc[4] < acc[1] or acc[5] < acc[2]:
                                    nxt = -1
                            elif acc[0] <= 0.0:
                                nxt = -1
                    if nxt >= 0:
                        i = nxt
                        descending = True
                    else:
                        r = finish(pk, prm[0], acc, ctx, sp)
                        if wp.static(count):
                            r[7] = sn[sp]
                        sp -= 1
                        i = par
        return r

    if _core:
        return traverse
    if bounds:

        @wp.func(inline=True)
        def evaluate_bounds(m: ModelArrays, ctx: BlockRows):
            # the block's cube (cells corner ... corner + 8) grown by 1e-4:
            # it meets every box a sub-block's cube meets
            c = grid_point(ctx.origin, ctx.h, ctx.corner[0] + 4, ctx.corner[1] + 4, ctx.corner[2] + 4)
            return traverse(m, c, ctx.h * (3.0 + ctx.half) * 1.0001, 0, ctx)

        return evaluate_bounds
    if array:

        @wp.func(inline=True)
        def evaluate_block(m: ModelArrays, ctx: BlockRows):
            c, half = block_center(ctx)
            return traverse(m, c, half, 0, ctx)

        return evaluate_block

    @wp.func(inline=True)
    def evaluate(m: ModelArrays, p: wp.vec3, radius: float):
        return traverse(m, p, radius, 0, BlockRows())

    return evaluate


@wp.func
def cubic_guess(fm: float, f0: float, f1: float, f2: float):
    """Root in (0, 1) of the cubic through (-1, fm), (0, f0), (1, f1), (2, f2)
    (f0, f1 of opposite signs), by Newton steps from the linear guess; the
    linear guess when the cubic's root leaves the interval. A starting point
    for :func:`make_segment_root`'s search from the samples around an edge."""
    c1 = -fm / 3.0 - 0.5 * f0 + f1 - f2 / 6.0
    c2 = 0.5 * fm - f0 + 0.5 * f1
    c3 = (f2 - fm) / 6.0 + 0.5 * (f0 - f1)
    lin = f0 / (f0 - f1)
    t = lin
    for _k in range(4):
        v = f0 + t * (c1 + t * (c2 + t * c3))
        d = c1 + t * (2.0 * c2 + 3.0 * t * c3)
        if d == 0.0:
            return lin
        t = t - v / d
    if t > 0.0 and t < 1.0:
        return t
    return lin


@wp.func
def hermite_root(t: float, f: float, slope: float, ta: float, fa: float, tb: float, fb: float, start: float):
    """Root near ``start`` of the cubic with value ``f`` and slope ``slope`` at
    ``t`` through (ta, fa) and (tb, fb) (ta < t < tb), by Newton steps on the
    cubic; -1 when it is degenerate. Uses the bracket's values as well as the
    derivative, so it converges in fewer field evaluations than Newton's
    tangent where F bends within a cell (SPEC 2.1 step 4)."""
    sa = ta - t
    sb = tb - t
    ra = fa - f - slope * sa
    rb = fb - f - slope * sb
    det = sa * sa * sb * sb * (sb - sa)
    if not (wp.abs(det) > 1.0e-30):
        return -1.0
    c2 = (ra * sb * sb * sb - rb * sa * sa * sa) / det
    c3 = (sa * sa * rb - sb * sb * ra) / det
    x = start - t
    for _k in range(5):
        d = slope + x * (2.0 * c2 + 3.0 * c3 * x)
        if d == 0.0:
            return -1.0
        x = x - (f + x * (slope + x * (c2 + x * c3))) / d
    return t + x


@wp.func
def falloff_root(t: float, f: float, slope: float, te: float, fe: float, iso: float):
    """Root between ``t`` and ``te`` of the quadratic in falloff space through
    F's value ``f`` and slope ``slope`` at ``t`` and the value ``fe`` at the
    bracket's other end ``te`` (values minus ``iso``, of opposite signs); -1
    where it does not apply (a cubic that also takes the slope at ``te``
    where that is an earlier step's point took more evaluations on towers,
    2.94 -> 2.95 per vertex at h = 0.14). The falloff space is ``s = 1 - F^(1/3)``: for one
    Wyvill primitive ``F = (1 - (d / R)^2)^3``, so ``s = (d / R)^2``, the squared
    distance to the skeleton, which is exactly quadratic along a line near a
    point, a segment's or a box's edge and a plate's face (where ``F`` itself
    bends from 0 to 1 within a cell when ``R`` is near the cell size). It
    applies where both ``F`` lie in (0, 1) and ``0 < iso < 1``; a blend of
    several primitives is near one of them close to its surface, and the
    search's bracket keeps any step safe where it is not."""
    fa = f + iso
    fb = fe + iso
    if not (fa > 0.0 and fa < 1.0 and fb > 0.0 and fb < 1.0 and iso > 0.0 and iso < 1.0):
        return -1.0
    ca = wp.cbrt(fa)
    s = 1.0 - ca
    ds = -slope / (3.0 * ca * ca)
    target = 1.0 - wp.cbrt(iso)
    dt = te - t
    if dt == 0.0:
        return -1.0
    qa = ((1.0 - wp.cbrt(fb)) - s - ds * dt) / (dt * dt)
    qc = s - target
    # s(t + x) - target = qc + ds x + qa x^2 changes sign on (0, dt): one root there
    x = float(-1.0e30)
    if wp.abs(qa * dt) <= 1.0e-6 * wp.abs(ds):
        if ds != 0.0:
            x = -qc / ds
    else:
        disc = ds * ds - 4.0 * qa * qc
        if disc >= 0.0:
            q = -0.5 * (ds + wp.where(ds >= 0.0, 1.0, -1.0) * wp.sqrt(disc))
            x1 = q / qa
            x2 = float(-1.0e30)
            if q != 0.0:
                x2 = qc / q
            x = x1
            if not (x1 * dt > 0.0 and wp.abs(x1) < wp.abs(dt)):
                x = x2
    if x * dt > 0.0 and wp.abs(x) < wp.abs(dt):
        return t + x
    return -1.0


def make_segment_root(evaluate, falloff_space: bool = False):
    """A root search on segments, for polygonization and isosurface stuffing.

    ``evaluate`` is a point-mode traversal with derivatives (:func:`make_evaluate`).
    The returned ``segment_root(m, p0, step, f0, f1, t0, iso, tolerance,
    max_iterations) -> (vec7 r, t, evaluations)`` starts at ``t0`` (e.g.
    :func:`cubic_guess`; outside (0, 1): the linear guess) and finds ``t`` in [0, 1] with
    ``|F(p0 + t step) - iso| <= tolerance``, given the values ``f0``, ``f1``
    (minus ``iso``, of opposite sides) at the ends: a Newton-type search along
    the segment with the analytic derivative, each step going to the root of
    the cubic that has F's value and slope at ``t`` and passes through the
    bracket's end values (:func:`hermite_root`; Newton's tangent step when
    that cubic has no root in the bracket), safeguarded by the bracket
    (Press et al.'s rtsafe: a step that leaves the bracket or fails to halve
    the previous one falls back to bisection). ``r`` is the evaluation at ``t`` (value,
    gradient, colour); if ``max_iterations`` run out, the best point found.

    With ``falloff_space`` each step first tries :func:`falloff_root` (the
    quadratic in ``s = 1 - F^(1/3)`` through the value and slope at ``t`` and
    the value at the bracket's other end), which is exact for one Wyvill
    primitive whose squared distance is quadratic along the segment, and
    falls back to the cubic above where it does not apply (towers h = 0.05:
    vertices whose second evaluation meets the tolerance 41% -> 90% on
    z-edges, 69% -> 83% on x- and y-edges).
    """

    @wp.func(inline=True)
    def segment_root(
        m: ModelArrays,
        p0: wp.vec3,
        step: wp.vec3,
        f0: float,
        f1: float,
        t0: float,
        iso: float,
        tolerance: float,
        max_iterations: int,
    ):
        ta = float(0.0)
        tb = float(1.0)
        fa = f0
        fb = f1
        t = fa / (fa - f1)
        if t0 > 0.0 and t0 < 1.0:
            t = t0
        dx_old = float(1.0)
        best = vec7()
        best_t = t
        best_f = float(1.0e30)
        count = int(0)
        for _it in range(max_iterations):
            r = evaluate(m, p0 + t * step, 0.0)
            count += 1
            ft = r[0] - iso
            if wp.abs(ft) < best_f:
                best_f = wp.abs(ft)
                best = r
                best_t = t
            if wp.abs(ft) <= tolerance:
                break
            pa = ta
            pfa = fa
            pb = tb
            pfb = fb
            slope = r[1] * step[0] + r[2] * step[1] + r[3] * step[2]
            if (ft >= 0.0) == (fa >= 0.0):
                ta = t
                fa = ft
            else:
                tb = t
                fb = ft
            tn = float(-1.0)
            if slope != 0.0:
                tn = t - ft / slope
            # the cubic through the bracket's ends with the tangent at t, from the Newton point
            th = float(-1.0)
            if wp.static(falloff_space):
                # the other end of the new bracket lies on the other side of the root from t
                if ta == t:
                    th = falloff_root(t, ft, slope, tb, fb, iso)
                else:
                    th = falloff_root(t, ft, slope, ta, fa, iso)
            if not (th > ta and th < tb):
                start = wp.clamp(wp.where(tn > 0.0, tn, 0.5 * (ta + tb)), ta, tb)
                th = hermite_root(t, ft, slope, pa, pfa, pb, pfb, start)
            if th > ta and th < tb:
                tn = th
            if tn > ta and tn < tb and wp.abs(tn - t) < 0.5 * dx_old:
                dx_old = wp.abs(tn - t)
                t = tn
            else:
                dx_old = 0.5 * (tb - ta)
                t = 0.5 * (ta + tb)
        return best, best_t, count

    return segment_root


def make_kernel(prune: bool, derivatives: bool):
    """Kernel evaluating points[offset : offset + dim] (range-split on the CPU)."""
    evaluate = make_evaluate(prune, derivatives=derivatives)

    @wp.kernel(enable_backward=False, module="unique")
    def evaluate_points_kernel(
        m: ModelArrays,
        points: wp.array(dtype=wp.vec3),
        offset: int,
        values: wp.array(dtype=wp.float32),
        gradients: wp.array(dtype=wp.vec3),
        colors: wp.array(dtype=wp.vec3),
    ):
        tid = wp.tid() + offset
        r = evaluate(m, points[tid], 0.0)
        values[tid] = r[0]
        if wp.static(derivatives):
            gradients[tid] = wp.vec3(r[1], r[2], r[3])
            colors[tid] = wp.vec3(r[4], r[5], r[6])

    return evaluate_points_kernel


def make_interval_kernel():
    """Kernel bounding F over balls: ``bounds[i] = (F_min, F_max)`` over ball ``(centers[i], radii[i])``."""
    evaluate = make_evaluate(True, interval=True)

    @wp.kernel(enable_backward=False, module="unique")
    def bound_balls_kernel(
        m: ModelArrays,
        centers: wp.array(dtype=wp.vec3),
        radii: wp.array(dtype=wp.float32),
        offset: int,
        bounds: wp.array(dtype=wp.vec2),
    ):
        tid = wp.tid() + offset
        r = evaluate(m, centers[tid], radii[tid])
        bounds[tid] = wp.vec2(r[0], r[1])

    return bound_balls_kernel


def make_grid_kernel():
    """Kernel filling a dense grid of F values, one thread per 8^3 block of
    grid points (array mode: one tree walk per block)."""
    evaluate_block = make_evaluate(True, derivatives=False, array=True)

    @wp.kernel(enable_backward=False, module="unique")
    def grid_blocks_kernel(
        m: ModelArrays,
        origin: wp.vec3,
        h: float,
        shape: wp.vec3i,
        blocks: wp.vec3i,
        first_block: int,
        rows: wp.array(dtype=wp.float32),
        result_slot: int,
        offset: int,
        values: wp.array3d(dtype=wp.float32),
    ):
        t = wp.tid() + offset
        b = first_block + t
        corner = wp.vec3i(
            (b % blocks[0]) * _BSIDE, ((b // blocks[0]) % blocks[1]) * _BSIDE, (b // (blocks[0] * blocks[1])) * _BSIDE
        )
        ctx = block_rows(rows, t, result_slot, origin, h, corner)
        want = ctx.base + (result_slot + 1) * _BPOINTS
        for l in range(_BPOINTS):
            gx = ctx.corner[0] + l % _BSIDE
            gy = ctx.corner[1] + (l // _BSIDE) % _BSIDE
            gz = ctx.corner[2] + l // (_BSIDE * _BSIDE)
            rows[want + l] = wp.where(gx < shape[0] and gy < shape[1] and gz < shape[2], 1.0, 0.0)
        r = evaluate_block(m, ctx)
        for l in range(_BPOINTS):
            if rows[want + l] != 0.0:
                values[corner[0] + l % _BSIDE, corner[1] + (l // _BSIDE) % _BSIDE, corner[2] + l // (_BSIDE * _BSIDE)] = block_result(ctx, r, l)

    return grid_blocks_kernel


def make_block_bounds_kernel():
    """Kernel bounding F over the 64 sub-blocks (2^3 cells) of 8^3-cell grid
    blocks, one thread per block (bounds rows: one tree walk per block)."""
    evaluate_bounds = make_evaluate(True, interval=True, array=True)

    @wp.kernel(enable_backward=False, module="unique")
    def bound_blocks_kernel(
        m: ModelArrays,
        origin: wp.vec3,
        h: float,
        blocks: wp.array(dtype=wp.vec3i),
        first_block: int,
        rows: wp.array(dtype=wp.float32),
        result_slot: int,
        offset: int,
        bounds: wp.array(dtype=wp.vec2),
    ):
        t = wp.tid() + offset
        b = first_block + t
        c = blocks[b]
        ctx = block_rows(rows, t, result_slot, origin, h, wp.vec3i(c[0] * _BSIDE, c[1] * _BSIDE, c[2] * _BSIDE))
        r = evaluate_bounds(m, ctx)
        for j in range(_SUBS):
            s = sub_bounds(ctx, r, j)
            bounds[b * _SUBS + j] = wp.vec2(s[0], s[1])

    return bound_blocks_kernel
