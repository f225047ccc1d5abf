"""The root-search building blocks of vertex placement (polygonizer, tetrahedralizer):
the cubic start from four samples, the Hermite step, and the safeguarded search."""

import numpy as np
import pytest
import warp as wp

import warpblob as wb
from reference import reference_evaluate
from warpblob.field._engine import model_arrays
from warpblob.field._kernels import (
    ModelArrays, cubic_guess, falloff_root, hermite_root, make_evaluate, make_segment_root,
)  # fmt: skip
from warpblob._linearize import linearize

segment_root = make_segment_root(make_evaluate(True))
segment_root_falloff = make_segment_root(make_evaluate(True), falloff_space=True)


@wp.kernel
def _cubic_kernel(c: wp.array(dtype=wp.vec4), guess: wp.array(dtype=float), herm: wp.array(dtype=float)):
    i = wp.tid()
    q = c[i]  # p(t) = q0 + q1 t + q2 t^2 + q3 t^3
    fm = q[0] - q[1] + q[2] - q[3]
    f0 = q[0]
    f1 = q[0] + q[1] + q[2] + q[3]
    f2 = q[0] + 2.0 * q[1] + 4.0 * q[2] + 8.0 * q[3]
    guess[i] = cubic_guess(fm, f0, f1, f2)
    t = 0.3
    f = q[0] + t * (q[1] + t * (q[2] + t * q[3]))
    slope = q[1] + t * (2.0 * q[2] + 3.0 * t * q[3])
    herm[i] = hermite_root(t, f, slope, 0.0, f0, 1.0, f1, 0.5)


def _random_cubics(rng, n):
    """Cubics with exactly one root in (0, 1), well inside it, and a nonzero slope there."""
    out, roots = [], []
    while len(out) < n:
        r = rng.uniform(0.15, 0.85)
        a, b = rng.uniform(-2.0, 2.0, 2)
        # (t - r)(a t^2 + b t + c) with the quadratic factor positive on [0, 1]
        c = abs(a) + abs(b) + rng.uniform(0.5, 1.5)
        q = np.polynomial.polynomial.polymul([-r, 1.0], [c, b, a])
        out.append(q * rng.choice([-1.0, 1.0]))
        roots.append(r)
    return np.array(out, dtype=np.float32), np.array(roots)


def test_cubic_start_and_hermite_step_find_the_root_of_a_cubic():
    rng = np.random.default_rng(2)
    q, roots = _random_cubics(rng, 200)
    guess = wp.zeros(200, dtype=float)
    herm = wp.zeros(200, dtype=float)
    wp.launch(_cubic_kernel, dim=200, inputs=[wp.array(q, dtype=wp.vec4), guess, herm], device="cpu")
    # a value, a slope and two values fix a cubic: the Hermite step is exact
    np.testing.assert_allclose(herm.numpy(), roots, atol=2e-4)
    # the start takes four Newton steps on the cubic through the four samples
    # from the linear guess: exact when they converge, never worse than that guess
    g = guess.numpy()
    f0, f1 = q[:, 0], q.sum(axis=1)
    linear = f0 / (f0 - f1)
    assert np.all((g > 0.0) & (g < 1.0))
    assert np.mean(np.abs(g - roots) < 2e-4) > 0.95
    assert np.all(np.abs(g - roots) <= np.abs(linear - roots) + 2e-4)


@wp.kernel
def _segments_kernel(
    m: ModelArrays,
    p0: wp.array(dtype=wp.vec3),
    step: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec2),
    tol: float,
    t_out: wp.array(dtype=float),
    count: wp.array(dtype=int),
):
    i = wp.tid()
    r, t, n = segment_root(m, p0[i], step[i], f[i][0], f[i][1], -1.0, 0.5, tol, 40)
    t_out[i] = t
    count[i] = n


@wp.kernel
def _segments_falloff_kernel(
    m: ModelArrays,
    p0: wp.array(dtype=wp.vec3),
    step: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec2),
    tol: float,
    t_out: wp.array(dtype=float),
    count: wp.array(dtype=int),
):
    i = wp.tid()
    _r, t, n = segment_root_falloff(m, p0[i], step[i], f[i][0], f[i][1], -1.0, 0.5, tol, 40)
    t_out[i] = t
    count[i] = n


@wp.kernel
def _falloff_root_kernel(
    q: wp.array(dtype=wp.vec4), iso: float, out: wp.array(dtype=float)
):  # fmt: skip
    i = wp.tid()
    c = q[i]  # (t, F(t) - iso, dF/dt(t), F(te) - iso) with te = 1 - t's side
    out[i] = falloff_root(c[0], c[1], c[2], wp.where(c[0] < 0.5, 1.0, 0.0), c[3], iso)


def test_falloff_root_is_exact_for_one_wyvill_point():
    """Along a line through a Wyvill point primitive, s = 1 - F^(1/3) is the
    squared distance over R^2, a quadratic: the step from one value and slope
    and the value at the bracket's other end lands on the analytic root
    (the sphere of radius R sqrt(1 - iso^(1/3)))."""
    rng = np.random.default_rng(7)
    iso, radius = 0.5, 1.0
    rows, roots = [], []
    while len(rows) < 300:
        c = rng.normal(size=3) * 0.3  # line p(t) = a + t (b - a), centre c
        a = rng.uniform(-0.2, 0.2, 3)
        d = rng.normal(size=3)
        d *= rng.uniform(0.5, 0.9) / np.linalg.norm(d)
        rel, dd = a - c, d
        # |rel + t dd|^2 = r_iso^2, the root in (0, 1)
        r_iso2 = radius**2 * (1.0 - iso ** (1.0 / 3.0))
        qa, qb, qc = dd @ dd, 2.0 * rel @ dd, rel @ rel - r_iso2
        disc = qb * qb - 4.0 * qa * qc
        if disc <= 0.0:
            continue
        t0 = rng.uniform(0.05, 0.95)
        te = 1.0 if t0 < 0.5 else 0.0
        both = (-qb + np.array([1.0, -1.0]) * np.sqrt(disc)) / (2.0 * qa)
        between = both[(both - t0) * (te - t0) > 0.0]
        # one crossing between t0 and te, not grazing (a float32 slope near 0 loses the root's digits)
        if len(between) != 1 or np.sqrt(disc) < 0.1 * qa or abs(t0 - between[0]) < 1e-3:
            continue
        root = between[0]

        def field(t, rel=rel, dd=dd):
            x2 = np.sum((rel + t * dd) ** 2) / radius**2
            return (1.0 - x2) ** 3 if x2 < 1.0 else 0.0

        f0, fe = field(t0) - iso, field(te) - iso
        if f0 * fe >= 0.0 or not (0.0 < fe + iso < 1.0) or not (0.0 < f0 + iso < 1.0):
            continue
        x2 = np.sum((rel + t0 * dd) ** 2) / radius**2
        slope = 3.0 * (1.0 - x2) ** 2 * (-2.0 * (rel + t0 * dd) @ dd / radius**2)
        rows.append((t0, f0, slope, fe))
        roots.append(root)
    out = wp.zeros(len(rows), dtype=float)
    q = wp.array(np.array(rows, np.float32), dtype=wp.vec4)
    wp.launch(_falloff_root_kernel, dim=len(rows), inputs=[q, iso, out], device="cpu")
    np.testing.assert_allclose(out.numpy(), roots, atol=5e-5)


@pytest.mark.parametrize("falloff_space", [False, True])
@pytest.mark.parametrize("name", ["steep_box", "blend"])
def test_segment_root_reaches_the_tolerance_on_every_crossing_segment(name, falloff_space):
    """Segments that cross the surface, some far longer than the falloff
    radius (F is nearly a step along them): every search ends inside the
    segment with |F - 0.5| <= tolerance, checked by the numpy reference,
    with the falloff-space step or without."""
    if name == "steep_box":
        model = wb.Box((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5), 0.05)
    else:
        model = wb.Blend(wb.Point((0, 0, 0), 1.0), wb.Segment((0.3, 0, 0), (1.2, 0.4, 0), 0.5))
    rng = np.random.default_rng(4)
    a = rng.uniform(-1.5, 1.5, (20000, 3))
    b = a + rng.normal(size=(20000, 3)) * rng.uniform(0.05, 1.0, (20000, 1))
    fa = reference_evaluate(model, a)[0] - 0.5
    fb = reference_evaluate(model, b)[0] - 0.5
    cross = (fa * fb < 0) & (np.abs(fa) > 1e-3) & (np.abs(fb) > 1e-3)
    assert cross.sum() > 200, "test set-up: too few crossing segments"
    a, b, fa, fb = a[cross], b[cross], fa[cross], fb[cross]
    n = len(a)
    # the search is given F at the float32 end points the kernel evaluates
    a32 = a.astype(np.float32)
    s32 = (b - a).astype(np.float32)
    fa = reference_evaluate(model, a32.astype(np.float64))[0] - 0.5
    fb = reference_evaluate(model, (a32 + s32).astype(np.float64))[0] - 0.5
    keep = (fa * fb < 0)
    t = wp.zeros(n, dtype=float)
    count = wp.zeros(n, dtype=int)
    m = model_arrays(linearize(model), "cpu")
    wp.launch(
        _segments_falloff_kernel if falloff_space else _segments_kernel, dim=n,
        inputs=[m, wp.array(a32, dtype=wp.vec3), wp.array(s32, dtype=wp.vec3),
                wp.array(np.column_stack([fa, fb]).astype(np.float32), dtype=wp.vec2), 1e-4, t, count],
        device="cpu",
    )  # fmt: skip
    t = t.numpy()[keep]
    assert np.all((t >= 0.0) & (t <= 1.0))
    f = reference_evaluate(model, (a32[keep] + t[:, None] * s32[keep]).astype(np.float32).astype(np.float64))[0]
    assert np.abs(f - 0.5).max() <= 1e-4 + 2e-6
    assert np.all(count.numpy()[keep] < 40), "a search ran out of iterations"
