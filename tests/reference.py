"""An independent float64 numpy reference evaluator of warpblob models.

It recurses over the *tree* (``warpblob.tree`` nodes), never over the
linearized form, and measures every distance from the user-level attributes
of the primitives directly in 3-D (no canonical local frames, no kernel data
blocks). Only ``Sketch.evaluate`` (the spline ``s(u)``; its gradient is
re-derived here from ``centers``/``weights``/``affine``) and the Sweep's
parallel-transported frames (``_rotations``, ``_lengths``, ``path``) are
reused from the tree.

Gradients are **analytic** (chain rule through falloff, distance, operators,
warps and transforms); :func:`reference_fd_gradient` gives central finite
differences of the float64 field for cross-checking.

Conventions (see ``warpblob/tree/_operators.py``):

* primitive field ``g(d / R)``, ``g(x) = (1 - x^2)^3`` on [0, 1), 1 for
  ``x <= 0``, 0 for ``x >= 1``;
* Blend = sum, Union = max, Intersection = min, Difference(a, b) =
  min(Fa, 1 - min(Fb, 1)), SmoothBlend(k) = (sum F_i^k)^(1/k);
* colour: black where F == 0; blends take the F-weighted (F^k for smooth
  blends) mean; union / intersection take the deciding child (strict
  comparison, first child wins ties); difference takes a's colour when
  Fa <= 1 - min(Fb, 1), else b's (with gradient -grad Fb, 0 where Fb >= 1),
  except where Fb == 0 (then Fa > 1 is clamped to 1 and keeps a's colour:
  b has no colour there; the operators' docstring does not spell this out).
"""

from __future__ import annotations

import numpy as np

from warpblob.tree import (
    Bend,
    Blend,
    Box,
    Cone,
    Difference,
    Disc,
    Inflate,
    Intersection,
    Point,
    Polygon,
    Revolve,
    Ring,
    Segment,
    SmoothBlend,
    Sweep,
    Taper,
    Transform,
    Twist,
    Union,
)

__all__ = ["reference_evaluate", "reference_evaluate_full", "reference_fd_gradient", "reference_field", "Result"]

_EPS32 = float(np.finfo(np.float32).eps)  # 2**-23
#: float32 rounding steps allowed per unit of sum |w_i K(r_i)| + |affine terms| in
#: the float32 spline (measured: the engine stays within ~2 of them).
SPLINE_ULPS = 4.0


# ----------------------------------------------------------------------------
# small vector helpers (rows are points)


def _dot(a, b):
    return np.einsum("ij,ij->i", a, b)


def _norm(a):
    return np.sqrt(_dot(a, a))


def _safe_unit(v, n):
    """v / n row-wise, 0 where n == 0."""
    out = np.zeros_like(v)
    ok = n > 0.0
    out[ok] = v[ok] / n[ok, None]
    return out


def _closest_on_segment(p, a, b):
    """Closest points on the 3-D segment [a, b] to the rows of ``p``."""
    ab = b - a
    ll = float(ab @ ab)
    if ll == 0.0:
        return np.broadcast_to(a, p.shape).copy()
    t = np.clip((p - a) @ ab / ll, 0.0, 1.0)
    return a + t[:, None] * ab


def _closest_on_segment2(u, a, b):
    """Closest points on 2-D segments: u (N, 2), a/b (N, 2) or (2,)."""
    a = np.broadcast_to(a, u.shape)
    b = np.broadcast_to(b, u.shape)
    ab = b - a
    ll = _dot(ab, ab)
    t = np.where(ll > 0.0, _dot(u - a, ab) / np.where(ll > 0.0, ll, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    return a + t[:, None] * ab


def _from_closest(p, q):
    """Distance and its gradient from the rows of ``p`` to their closest skeleton points ``q``."""
    v = p - q
    d = _norm(v)
    return d, _safe_unit(v, d)


def _any_perpendicular(n):
    h = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e = h - (h @ n) * n
    return e / np.linalg.norm(e)


# ----------------------------------------------------------------------------
# primitive distances: (d (N,), grad d (N, 3)) in the primitive's parent frame


def _dist_point(node, p):
    return _from_closest(p, np.broadcast_to(node.center, p.shape))


def _dist_segment(node, p):
    return _from_closest(p, _closest_on_segment(p, node.a, node.b))


def _disc_ring_frame(node, p):
    n = node.normal / np.linalg.norm(node.normal)
    rel = p - node.center
    h = rel @ n
    v = rel - h[:, None] * n
    rho = _norm(v)
    e = _safe_unit(v, rho)
    e[rho == 0.0] = _any_perpendicular(n)
    return rho, e


def _dist_disc(node, p):
    rho, e = _disc_ring_frame(node, p)
    q = node.center + np.minimum(rho, node.size)[:, None] * e
    return _from_closest(p, q)


def _dist_ring(node, p):
    rho, e = _disc_ring_frame(node, p)
    return _from_closest(p, node.center + node.size * e)


def _dist_cone(node, p):
    """Solid truncated cone: 2-D distance to the trapezoid (rho, t) then back to 3-D."""
    a, b = node.a, node.b
    length = float(np.linalg.norm(b - a))
    axis = (b - a) / length
    ra, rb = node.radius_a, node.radius_b
    rel = p - a
    t = rel @ axis
    v = rel - t[:, None] * axis
    rho = _norm(v)
    e = _safe_unit(v, rho)
    e[rho == 0.0] = _any_perpendicular(axis)
    u = np.column_stack([rho, t])
    corners = np.array([[0.0, 0.0], [ra, 0.0], [rb, length], [0.0, length]])
    best = np.full(len(p), np.inf)
    closest = np.zeros_like(u)
    for k in range(4):
        c = _closest_on_segment2(u, corners[k], corners[(k + 1) % 4])
        dd = _norm(u - c)
        take = dd < best
        best[take] = dd[take]
        closest[take] = c[take]
    inside = (t >= 0.0) & (t <= length) & (rho <= ra + (rb - ra) * t / length)
    closest[inside] = u[inside]
    q = a + closest[:, 1:2] * axis + closest[:, 0:1] * e
    return _from_closest(p, q)


def _polygon_plane(points):
    center = points.mean(axis=0)
    nxt = np.roll(points, -1, axis=0)
    normal = np.sum(np.cross(points, nxt), axis=0)  # Newell / vector area
    normal /= np.linalg.norm(normal)
    e1 = points[1] - points[0]
    e1 = e1 - (e1 @ normal) * normal
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return center, normal, e1, e2


def _inside_polygon2(u, poly):
    """Even-odd crossing test: u (N, 2) against the closed 2-D polygon ``poly``."""
    inside = np.zeros(len(u), dtype=bool)
    n = len(poly)
    for k in range(n):
        (x0, y0), (x1, y1) = poly[k], poly[(k + 1) % n]
        crosses = (y0 > u[:, 1]) != (y1 > u[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = x0 + (u[:, 1] - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (u[:, 0] < xc)
    return inside


def _dist_polygon(node, p):
    pts = np.asarray(node.points, dtype=np.float64)
    center, normal, e1, e2 = _polygon_plane(pts)
    rel = p - center
    h = rel @ normal
    u = np.column_stack([rel @ e1, rel @ e2])
    poly = np.column_stack([(pts - center) @ e1, (pts - center) @ e2])
    best = np.full(len(p), np.inf)
    closest = np.zeros_like(p)
    for k in range(len(pts)):
        q = _closest_on_segment(p, pts[k], pts[(k + 1) % len(pts)])
        dd = _norm(p - q)
        take = dd < best
        best[take] = dd[take]
        closest[take] = q[take]
    inside = _inside_polygon2(u, poly)
    closest[inside] = p[inside] - h[inside, None] * normal
    return _from_closest(p, closest)


def _dist_box(node, p):
    c, h = node.center, node.half_extents
    return _from_closest(p, c + np.clip(p - c, -h, h))


def _sketch_outside(sketch, u, cutoff):
    """``o(u) = max(-s(u), e(u), 0)``, its gradient (N, 2), ``s``, grad ``s`` and error bounds.

    ``s`` is only evaluated where the rectangle distance ``e < cutoff`` (the
    support radius): elsewhere ``o >= e >= R`` and the field is exactly 0
    whatever ``s`` is, so ``s`` is reported as ``-e`` there.

    Returns ``(o, grad_o, s, grad_s, o_slack, s_slack)``: ``s_slack`` bounds the
    float32 error of ``s``; ``o_slack`` the resulting error of ``o`` (``o`` is
    1-Lipschitz in ``s``, and independent of it where ``e`` or 0 wins clearly).
    """
    c = np.clip(u, sketch.lower, sketch.upper)
    ev = u - c
    e = _norm(ev)
    grad_e = _safe_unit(ev, e)
    near = e < cutoff
    s = -e.copy()
    grad_s = np.zeros_like(u)
    s_slack = np.zeros(len(u))
    if np.any(near):
        un = u[near]
        s[near] = sketch.evaluate(un)
        diff = un[:, None, :] - sketch.centers[None, :, :]
        r = np.sqrt(np.sum(diff * diff, axis=2))
        with np.errstate(divide="ignore", invalid="ignore"):
            logr = np.log(np.where(r > 0.0, r, 1.0))
            coef = np.where(r > 0.0, 2.0 * logr + 1.0, 0.0)
        # d/du (r^2 ln r) = (2 ln r + 1) (u - m)
        grad_s[near] = np.einsum("nm,nmk->nk", coef * sketch.weights[None, :], diff) + sketch.affine[:2]
        # float32 conditioning of s(u): every term of the sum is rounded (weights,
        # r, log r, products, accumulation), so a float32 evaluation is only good
        # to about eps32 * sum |terms| (the spline weights are O(10) and cancel).
        terms = np.abs(r * r * logr) @ np.abs(sketch.weights) + np.abs(un) @ np.abs(sketch.affine[:2]) + abs(sketch.affine[2])
        s_slack[near] = SPLINE_ULPS * _EPS32 * terms
    o = np.zeros(len(u))
    grad_o = np.zeros_like(u)
    take_s = -s > 0.0
    o[take_s] = -s[take_s]
    grad_o[take_s] = -grad_s[take_s]
    take_e = e > o
    o[take_e] = e[take_e]
    grad_o[take_e] = grad_e[take_e]
    o_slack = np.where(-s + s_slack >= np.maximum(e, 0.0), s_slack, 0.0)
    return o, grad_o, s, grad_s, o_slack, s_slack


def _dist_inflate(node, p):
    sk = node.sketch
    u = p[:, :2]
    z = p[:, 2]
    o, grad_o, s, grad_s, o_slack, s_slack = _sketch_outside(sk, u, node.radius)
    t_raw = s / sk.depth
    t = np.clip(t_raw, 0.0, 1.0)
    half = node.thickness * (1.0 - (1.0 - t) ** 2)
    grad_t = np.where(((t_raw > 0.0) & (t_raw < 1.0))[:, None], grad_s / sk.depth, 0.0)
    grad_half = (node.thickness * 2.0 * (1.0 - t))[:, None] * grad_t
    m = np.abs(z) - half
    pos = m > 0.0
    m = np.where(pos, m, 0.0)
    d = np.sqrt(o * o + m * m)
    grad_m = np.zeros_like(p)
    grad_m[:, :2] = -grad_half
    grad_m[:, 2] = np.sign(z)
    grad_m[~pos] = 0.0
    grad = np.zeros_like(p)
    grad[:, :2] = o[:, None] * grad_o
    grad += m[:, None] * grad_m
    # h moves by at most 2 thickness / depth per unit of s (where 0 < s < depth)
    h_slack = 2.0 * node.thickness / sk.depth * s_slack
    h_slack = np.where((s + s_slack > 0.0) & (s - s_slack < sk.depth) & (np.abs(z) - half + h_slack > 0.0), h_slack, 0.0)
    return d, _safe_unit(grad, d), o_slack + h_slack


def _dist_revolve(node, p):
    axis = node.axis / np.linalg.norm(node.axis)
    rel = p - node.center
    y = rel @ axis
    v = rel - y[:, None] * axis
    x = _norm(v)
    e = _safe_unit(v, x)
    o, grad_o, _, _, o_slack, _ = _sketch_outside(node.sketch, np.column_stack([x, y]), node.radius)
    return o, grad_o[:, 0:1] * e + grad_o[:, 1:2] * axis, o_slack


def _dist_sweep(node, p):
    best = np.full(len(p), np.inf)
    grad = np.zeros_like(p)
    slack = np.zeros(len(p))
    for origin, rot, length in zip(node.path[:-1], node._rotations, node._lengths):
        local = (p - origin) @ rot  # columns of rot: normal, binormal, tangent
        o, grad_o, _, _, o_slack, _ = _sketch_outside(node.sketch, local[:, :2], node.radius)
        slack = np.maximum(slack, o_slack)
        z = local[:, 2]
        past = np.maximum(np.maximum(-z, z - length), 0.0)
        dd = np.sqrt(o * o + past * past)
        gl = np.zeros_like(p)
        gl[:, :2] = o[:, None] * grad_o
        gl[:, 2] = np.where(z < 0.0, -past, np.where(z > length, past, 0.0))
        gl = _safe_unit(gl, dd)
        take = dd < best
        best[take] = dd[take]
        grad[take] = gl[take] @ rot.T
    return best, grad, slack


# order matters: subclasses before their bases (Triangle < Polygon, Cylinder < Cone)
_DISTANCES = [
    (Point, _dist_point),
    (Segment, _dist_segment),
    (Disc, _dist_disc),
    (Ring, _dist_ring),
    (Cone, _dist_cone),
    (Polygon, _dist_polygon),
    (Box, _dist_box),
    (Inflate, _dist_inflate),
    (Revolve, _dist_revolve),
    (Sweep, _dist_sweep),
]


def _falloff(x):
    """g(x) and g'(x)."""
    inner = (x > 0.0) & (x < 1.0)
    w = np.where(inner, 1.0 - x * x, 0.0)
    g = np.where(x <= 0.0, 1.0, np.where(inner, w**3, 0.0))
    dg = np.where(inner, -6.0 * x * w * w, 0.0)
    return g, dg


# ----------------------------------------------------------------------------
# warps: (warped point (N, 3), pull-back of a gradient at the warped point)


def _rodrigues(v, a, angle):
    c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
    return v * c + np.cross(a, v) * s + (v @ a)[:, None] * a * (1.0 - c)


def _warp_twist(node, p):
    a = node.axis / np.linalg.norm(node.axis)
    theta = -node.rate * (p @ a)
    q = _rodrigues(p, a, theta)

    def pull(g):
        # J = R + (a x q)(-rate a)^T  ->  J^T g = R^T g - rate a ((a x q) . g)
        return _rodrigues(g, a, -theta) - node.rate * _dot(np.cross(a, q), g)[:, None] * a

    return q, pull


def _warp_taper(node, p):
    a = node.axis / np.linalg.norm(node.axis)
    t = p @ a
    raw = 1.0 + node.slope * t
    s = np.maximum(raw, 0.05)
    ds = np.where(raw > 0.05, node.slope, 0.0)
    perp = p - t[:, None] * a
    q = t[:, None] * a + perp / s[:, None]

    def pull(g):
        ga = g @ a
        return ga[:, None] * a + (g - ga[:, None] * a) / s[:, None] - (ds / (s * s) * _dot(perp, g))[:, None] * a

    return q, pull


def _bend_side(node):
    """The unit vector the bend turns towards (``up``, negated for a negative rate).

    Older trees store it sign-adjusted as ``up``; newer ones keep the user's
    ``up`` and store the adjusted vector as ``side``.
    """
    side = getattr(node, "side", None)
    return np.asarray(node.up if side is None else side, dtype=np.float64)


def _warp_bend(node, p):
    d, u, rho = node.direction, _bend_side(node), node.rho
    w = np.cross(d, u)
    x, y, z = p @ d, p @ u, p @ w
    yy = rho - y
    theta = np.arctan2(x, yy)
    r = np.hypot(x, yy)
    q = (rho * theta)[:, None] * d + (rho - r)[:, None] * u + z[:, None] * w

    def pull(g):
        gx, gy, gz = g @ d, g @ u, g @ w
        fx = gx * rho * yy / (r * r) - gy * x / r
        fy = gx * rho * x / (r * r) + gy * yy / r
        return fx[:, None] * d + fy[:, None] * u + gz[:, None] * w

    return q, pull


_WARPS = [(Twist, _warp_twist), (Taper, _warp_taper), (Bend, _warp_bend)]


# ----------------------------------------------------------------------------
# the recursion


def _black(f, c):
    c = c.copy()
    c[f == 0.0] = 0.0
    return c


class Result:
    """Per-point reference results of one subtree.

    Attributes:
        f: field values (N,); grad: analytic gradients (N, 3); color: (N, 3).
        margin: smallest gap between the two candidates of a max / min
            decision (union, intersection, difference) that influences the
            result; gradients and colours may legitimately jump where it is ~0
            (inf where no such decision is involved).
        slack: first-order bound of the field error that a float32 evaluation
            of the sketch splines alone incurs (0 where no sketched primitive
            contributes); see ``SPLINE_ULPS``.
        smooth: True where a SmoothBlend with a non-zero field feeds the result
            (lets tests separate a known SmoothBlend defect from the rest).
    """

    __slots__ = ("f", "grad", "color", "margin", "smooth", "slack")

    def __init__(self, f, grad, color, margin, slack, smooth=None):
        self.f, self.grad, self.color, self.margin, self.slack = f, grad, color, margin, slack
        self.smooth = np.zeros(len(f), dtype=bool) if smooth is None else smooth

    def copy(self):
        return Result(
            self.f.copy(), self.grad.copy(), self.color.copy(), self.margin.copy(), self.slack.copy(), self.smooth.copy()
        )


def _primitive(node, p):
    for cls, fn in _DISTANCES:
        if isinstance(node, cls):
            out = fn(node, p)
            d, gd = out[0], out[1]
            dslack = out[2] if len(out) > 2 else np.zeros(len(p))
            g, dg = _falloff(d / node.radius)
            grad = (dg / node.radius)[:, None] * gd
            col = _black(g, np.broadcast_to(node.color, (len(p), 3)))
            return Result(g, grad, col, np.full(len(p), np.inf), np.abs(dg) / node.radius * dslack)
    return None


def _eval(node, p):
    """The :class:`Result` of ``node`` at the rows of ``p`` (float64)."""
    res = _primitive(node, p)
    if res is not None:
        return res
    if isinstance(node, Transform):
        m = node.matrix
        inv = np.linalg.inv(m[:3, :3])
        res = _eval(node.child, (p - m[:3, 3]) @ inv.T)
        res.grad = res.grad @ inv
        return res
    for cls, fn in _WARPS:
        if isinstance(node, cls):
            q, pull = fn(node, p)
            res = _eval(node.child, q)
            res.grad = pull(res.grad)
            return res
    kids = [_eval(c, p) for c in node.children]

    def live_margin():
        return np.min([np.where(r.f > 0.0, r.margin, np.inf) for r in kids], axis=0)

    def live_smooth():
        return np.any([(r.f > 0.0) & r.smooth for r in kids], axis=0)

    if isinstance(node, SmoothBlend):  # before Blend (subclass)
        k = node.k
        fk = sum(r.f**k for r in kids)
        f = fk ** (1.0 / k)
        pos = f > 0.0
        scale = np.where(pos, np.where(pos, f, 1.0) ** (1.0 - k), 0.0)
        grad = scale[:, None] * sum((r.f ** (k - 1.0))[:, None] * r.grad for r in kids)
        num = sum((r.f**k)[:, None] * r.color for r in kids)
        col = np.where(pos[:, None], num / np.where(pos, fk, 1.0)[:, None], 0.0)
        # the k-norm is 1-Lipschitz for the k-norm, hence for the 1-norm of the errors
        return Result(f, grad, col, live_margin(), sum(r.slack for r in kids), f > 0.0)
    if isinstance(node, (Union, Intersection)):  # Union before Blend (subclass)
        better = np.greater if isinstance(node, Union) else np.less
        out = kids[0].copy()
        for r in kids[1:]:
            take = better(r.f, out.f)
            for name in Result.__slots__[:5]:
                getattr(out, name)[take] = getattr(r, name)[take]
        if len(kids) > 1:
            gaps = np.sort(np.stack([np.abs(r.f - out.f) for r in kids]), axis=0)
            out.margin = np.minimum(out.margin, gaps[1])  # gaps[0] is the chosen child's 0
        out.slack = np.max([r.slack for r in kids], axis=0)  # max / min are 1-Lipschitz
        return out
    if isinstance(node, Blend):
        f = sum(r.f for r in kids)
        grad = sum(r.grad for r in kids)
        pos = f > 0.0
        num = sum(r.f[:, None] * r.color for r in kids)
        col = np.where(pos[:, None], num / np.where(pos, f, 1.0)[:, None], 0.0)
        return Result(f, grad, col, live_margin(), sum(r.slack for r in kids), live_smooth())
    if isinstance(node, Difference):
        a, b = kids
        nb = 1.0 - np.minimum(b.f, 1.0)
        keep_a = a.f <= nb
        f = np.where(keep_a, a.f, nb)
        grad = np.where(keep_a[:, None], a.grad, np.where((b.f < 1.0)[:, None], -b.grad, 0.0))
        # where b is empty (F_b == 0) and F_a > 1 the value is the constant 1 that
        # b's clamp imposes, but b has no colour there (black is reserved for
        # F == 0): a's colour is kept, as the engine does
        a_colour = keep_a | (b.f <= 0.0)
        col = _black(f, np.where(a_colour[:, None], a.color, b.color))
        margin = np.minimum(np.where(keep_a, a.margin, b.margin), np.abs(a.f - nb))
        margin = np.minimum(margin, np.where(~keep_a & (b.f > 0.0), b.f, np.inf))
        smooth = np.where(keep_a, a.smooth, b.smooth)
        return Result(f, grad, col, margin, np.maximum(a.slack, b.slack), smooth)
    raise TypeError(f"reference: unsupported node {node!r}")


def _as_points(points):
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.ascontiguousarray(p)


def reference_evaluate_full(node, points) -> Result:
    """The full :class:`Result` (values, gradients, colours, margin, slack) in float64."""
    return _eval(node, _as_points(points))


def reference_evaluate(node, points):
    """``(values (N,), gradients (N, 3), colors (N, 3))`` in float64 at ``points``."""
    r = _eval(node, _as_points(points))
    return r.f, r.grad, r.color


def reference_field(node, points):
    return _eval(node, _as_points(points)).f


def reference_fd_gradient(node, points, h=1e-6):
    """Central finite differences (step ``h``) of the float64 reference field."""
    p = _as_points(points)
    out = np.zeros_like(p)
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h
        out[:, k] = (reference_field(node, p + dp) - reference_field(node, p - dp)) / (2.0 * h)
    return out
