"""Tree validation (ModelError with the offending value) and bounding boxes."""

from __future__ import annotations

import numpy as np
import pytest

import warpblob as wb
from reference import reference_field
from test_field import PRIMITIVE_KINDS, make_primitive

P = wb.Point((0.0, 0.0, 0.0), 1.0)
Q = wb.Point((0.5, 0.0, 0.0), 1.0)
SQUARE = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]


def test_error_hierarchy():
    assert issubclass(wb.ModelError, wb.WarpblobError)
    assert issubclass(wb.ModelError, ValueError)


# (id, callable that must raise ModelError, text that must appear in the message)
BAD = [
    # non-positive radii / sizes
    ("point_radius_zero", lambda: wb.Point((0, 0, 0), 0.0), "0"),
    ("point_radius_negative", lambda: wb.Point((0, 0, 0), -1.5), "-1.5"),
    ("segment_radius_negative", lambda: wb.Segment((0, 0, 0), (1, 0, 0), -0.25), "-0.25"),
    ("disc_size_zero", lambda: wb.Disc((0, 0, 0), (0, 0, 1), 0.0, 1.0), "disc_radius"),
    ("ring_size_negative", lambda: wb.Ring((0, 0, 0), (0, 0, 1), -0.75, 1.0), "-0.75"),
    ("cylinder_radius_negative", lambda: wb.Cylinder((0, 0, 0), (0, 0, 1), -0.3, 1.0), "-0.3"),
    ("cone_radius_negative", lambda: wb.Cone((0, 0, 0), (0, 0, 1), -0.4, 0.2, 1.0), "-0.4"),
    ("box_radius_zero", lambda: wb.Box((0, 0, 0), (1, 1, 1), 0.0), "radius"),
    ("box_half_extent_negative", lambda: wb.Box((0, 0, 0), (1, -0.125, 1), 0.5), "-0.125"),
    ("inflate_radius_negative", lambda: wb.Inflate(wb.Sketch(SQUARE), radius=-0.6), "-0.6"),
    ("inflate_thickness_negative", lambda: wb.Inflate(wb.Sketch(SQUARE), thickness=-0.2), "-0.2"),
    ("revolve_radius_zero", lambda: wb.Revolve(wb.Sketch(SQUARE), radius=0.0), "radius"),
    ("sweep_radius_negative", lambda: wb.Sweep(wb.Sketch(SQUARE), [[0, 0, 0], [0, 0, 1]], radius=-0.9), "-0.9"),
    # non-finite coordinates
    ("point_center_nan", lambda: wb.Point((float("nan"), 0, 0), 1.0), "nan"),
    ("segment_end_inf", lambda: wb.Segment((0, 0, 0), (float("inf"), 0, 0), 1.0), "inf"),
    ("disc_center_inf", lambda: wb.Disc((0, -np.inf, 0), (0, 0, 1), 1.0, 1.0), "inf"),
    ("polygon_vertex_nan", lambda: wb.Polygon([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], 1.0), "nan"),
    ("radius_nan", lambda: wb.Point((0, 0, 0), float("nan")), "nan"),
    ("radius_inf", lambda: wb.Point((0, 0, 0), float("inf")), "inf"),
    ("translate_nan", lambda: P.translate((0, np.nan, 0)), "nan"),
    ("sketch_point_inf", lambda: wb.Sketch([[0, 0], [1, 0], [1, np.inf]]), "inf"),
    ("twist_rate_nan", lambda: wb.Twist(P, (0, 0, 1), float("nan")), "nan"),
    # zero-length directions
    ("disc_normal_zero", lambda: wb.Disc((0, 0, 0), (0, 0, 0), 1.0, 1.0), "(0, 0, 0)"),
    ("ring_normal_zero", lambda: wb.Ring((0, 0, 0), [0.0, 0.0, 0.0], 1.0, 1.0), "[0.0, 0.0, 0.0]"),
    ("segment_zero_length", lambda: wb.Segment((1, 2, 3), (1, 2, 3), 1.0), "(1, 2, 3)"),
    ("cone_zero_length", lambda: wb.Cone((1, 2, 3), (1, 2, 3), 0.2, 0.1, 1.0), "(1, 2, 3)"),
    ("twist_axis_zero", lambda: wb.Twist(P, (0, 0, 0), 1.0), "(0, 0, 0)"),
    ("taper_axis_zero", lambda: wb.Taper(P, (0, 0, 0), 0.1), "(0, 0, 0)"),
    ("bend_direction_zero", lambda: wb.Bend(P, (0, 0, 0), (0, 1, 0), 0.1), "(0, 0, 0)"),
    ("bend_up_parallel", lambda: wb.Bend(P, (1, 0, 0), (2, 0, 0), 0.1), "(2, 0, 0)"),
    ("revolve_axis_zero", lambda: wb.Revolve(wb.Sketch(SQUARE), axis=(0, 0, 0)), "(0, 0, 0)"),
    ("rotate_axis_zero", lambda: P.rotate((0, 0, 0), 1.0), "(0, 0, 0)"),
    # polygons
    ("polygon_collinear", lambda: wb.Polygon([[0, 0, 0], [1, 1, 1], [2.5, 2.5, 2.5]], 1.0), "2.5"),
    ("triangle_collinear", lambda: wb.Triangle((0, 0, 0), (1, 0, 0), (3.75, 0, 0), 1.0), "3.75"),
    ("polygon_too_few", lambda: wb.Polygon([[0, 0, 0], [1, 0, 0]], 1.0), "(2, 3)"),
    ("polygon_not_coplanar", lambda: wb.Polygon([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]], 1.0), "off the plane"),
    # sketches and sketched primitives
    ("sketch_self_intersecting", lambda: wb.Sketch([[0, 0], [2.5, 1.5], [2.5, 0], [0, 1]]), "cross"),
    ("sketch_degenerate", lambda: wb.Sketch([[0, 0], [1, 1], [2, 2]]), "area"),
    ("sketch_not_a_sketch", lambda: wb.Inflate("square"), "'square'"),
    ("revolve_profile_negative_x", lambda: wb.Revolve(wb.Sketch([[-0.5, 0], [1, 0], [1, 1], [0, 1]])), "-0.5"),
    ("sweep_repeated_point", lambda: wb.Sweep(wb.Sketch(SQUARE), [[0, 0, 0], [0, 0, 1], [0, 0, 1]]), "segment 1"),
    # operators
    ("blend_no_operand", lambda: wb.Blend(), "got 0"),
    ("union_empty_list", lambda: wb.Union([]), "got 0"),
    ("intersection_no_operand", lambda: wb.Intersection(), "got 0"),
    ("smooth_blend_one_operand", lambda: wb.SmoothBlend(P), "got 1"),
    ("difference_none_operand", lambda: wb.Difference(P, None), "None"),
    ("operand_not_a_node", lambda: wb.Blend(P, 3.5), "3.5"),
    ("smooth_blend_k_below_1", lambda: wb.SmoothBlend(P, Q, k=0.5), "0.5"),
    ("smooth_blend_k_nan", lambda: wb.SmoothBlend(P, Q, k=float("nan")), "nan"),
    # warps
    ("bend_rate_zero", lambda: wb.Bend(P, (1, 0, 0), (0, 1, 0), 0.0), "0"),
    ("bend_wraps_child", lambda: wb.Bend(wb.Segment((-3, 0, 0), (3, 0, 0), 0.5), rate=1.5), "1.5"),
    ("taper_folds_child", lambda: wb.Taper(wb.Segment((0, 0, -2), (0, 0, 2), 0.5), (0, 0, 1), -0.75), "-0.75"),
    # transforms
    ("scale_zero_vector", lambda: P.scale((1.0, 0.0, 2.0)), "(1.0, 0.0, 2.0)"),
    ("scale_zero_scalar", lambda: P.scale(0.0), "0.0"),
    ("transform_singular", lambda: P.transform([[2, 4, 0, 0], [1, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "4"),
    ("transform_bad_last_row", lambda: wb.Transform(P, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 7, 1]]), "7"),
    ("transform_nan", lambda: wb.Transform(P, np.full((4, 4), np.nan)), "nan"),
    ("transform_shape", lambda: wb.Transform(P, np.eye(3)), "array"),
    # colours
    ("color_out_of_range", lambda: wb.Point((0, 0, 0), 1.0, color=(1.0, 1.5, 0.0)), "1.5"),
    ("color_wrong_length", lambda: wb.Point((0, 0, 0), 1.0, color=(1.0, 0.5)), "(1.0, 0.5)"),
]


@pytest.mark.parametrize("make, text", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_parameter_raises_model_error(make, text):
    with pytest.raises(wb.ModelError) as info:
        make()
    assert isinstance(info.value, wb.WarpblobError)
    msg = str(info.value)
    assert text.lower() in msg.lower(), f"message {msg!r} does not show the offending value {text!r}"


def test_non_coplanar_message_names_the_vertex_and_offset():
    with pytest.raises(wb.ModelError, match=r"vertex \d is 0\.\d+ off the plane"):
        wb.Polygon([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.5]], 1.0)


def test_slightly_non_coplanar_polygon_within_tolerance_is_accepted():
    poly = wb.Polygon([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 1e-9]], 1.0)
    lo, hi = poly.bounds()
    assert np.all(np.isfinite(lo)) and np.all(hi - lo > 1.9)


def test_difference_with_one_operand_raises_model_error():
    with pytest.raises(wb.ModelError, match="got 1"):
        wb.Difference(P)


def test_difference_with_three_operands_raises_model_error():
    with pytest.raises(wb.ModelError, match="got 3"):
        wb.Difference(P, Q, P)


def test_self_intersecting_sketch_message_names_the_crossing_edges():
    with pytest.raises(wb.ModelError) as info:
        wb.Sketch([[0.0, 0.0], [2.5, 1.5], [2.5, 0.0], [0.0, 1.0]])
    msg = str(info.value)
    # a crossing edge's vertex, e.g. (2.5, 1.5), or the crossing edges' indices ("edges 0 and 2")
    assert "2.5" in msg or "1.5" in msg or any(f"{i} and {j}" in msg for i in range(4) for j in range(4)), msg


def test_sweep_path_that_turns_back_raises_model_error():
    with pytest.raises(wb.ModelError, match=r"turns back on itself at point 1 \(\[0\.0, 0\.0, 1\.0\]\)"):
        wb.Sweep(wb.Sketch(SQUARE), [[0, 0, 0], [0, 0, 1], [0, 0, 0.5]])


def test_sweep_path_with_a_right_angle_towards_the_normal_is_accepted():
    sweep = wb.Sweep(wb.Sketch(SQUARE), [[0, 0, 0], [0, 0, 1], [1, 0, 1]])
    assert sweep.primitive_count() == 1


def test_sweep_path_with_a_right_angle_is_accepted():
    sweep = wb.Sweep(wb.Sketch(SQUARE), [[0, 0, 0], [0, 0, 1], [0, 1, 1]])
    lo, hi = sweep.bounds()
    assert np.all(lo <= [0, 0, 0]) and np.all(hi >= [0, 1, 1])


def test_valid_edge_cases_are_accepted():
    nodes = [
        wb.Cone((0, 0, 0), (0, 0, 1), 0.0, 0.5, 1.0),  # a pointed cone
        wb.Box((0, 0, 0), (0.0, 0.0, 0.0), 1.0),  # a box that is a point
        wb.Inflate(wb.Sketch(SQUARE), thickness=0.0),
        wb.SmoothBlend(P, Q, k=1.0),
        wb.Bend(P, (1, 0, 0), (0, 1, 0), -0.3),
        wb.Taper(wb.Segment((0, 0, -2), (0, 0, 2), 0.5), (0, 0, 1), 0.2),
        P.scale(-1.0),  # a mirror is invertible
        wb.Revolve(wb.Sketch([[0.0, 0.0], [1, 0], [1, 1], [0, 1]])),  # touching the axis is fine
    ]
    for node in nodes:
        lo, hi = node.bounds()
        assert np.all(np.isfinite(lo)) and np.all(hi > lo), node


# ----------------------------------------------------------------------------
# bounds


def test_lone_point_bounds_are_center_plus_minus_radius():
    for c, r in (((0.0, 0.0, 0.0), 1.0), ((1.5, -2.0, 3.25), 0.3), ((-7.0, 0.1, 0.0), 12.0)):
        lo, hi = wb.Point(c, r).bounds()
        c = np.asarray(c)
        pad = 2e-3 * r  # BOX_PAD is 1e-3 of R
        assert np.all(lo <= c - r) and np.all(lo >= c - r - pad), (lo, c - r)
        assert np.all(hi >= c + r) and np.all(hi <= c + r + pad), (hi, c + r)


def test_bounds_are_copies():
    lo, hi = P.bounds()
    lo[:] = 99.0
    assert np.all(P.bounds()[0] < 0.0)


def _outside_points(model, rng, n=3000):
    """float32 points outside ``model.bounds()``: anywhere in a 1.5x box, and just outside each face."""
    lo, hi = model.bounds()
    size = hi - lo
    wide = (lo - 0.25 * size) + 1.5 * size * rng.random((n, 3))
    near = lo + size * rng.random((n, 3))
    axis = rng.integers(0, 3, size=n)
    side = rng.integers(0, 2, size=n)
    gap = 10.0 ** rng.uniform(-5, -2, size=n) * np.max(size)
    idx = np.arange(n)
    near[idx, axis] = np.where(side == 0, lo[axis] - gap, hi[axis] + gap)
    pts = np.vstack([wide, near]).astype(np.float32)
    p64 = pts.astype(np.float64)
    outside = np.any((p64 < lo) | (p64 > hi), axis=1)
    return pts[outside]


def _bounds_cases():
    cases = {f"primitive_{k}": (lambda rng, k=k: make_primitive(k, rng)) for k in PRIMITIVE_KINDS}

    def two(rng):
        return make_primitive("segment", rng), make_primitive("box", rng, (0.4, 0.2, 0.0))

    cases["blend"] = lambda rng: wb.Blend(*two(rng))
    cases["union"] = lambda rng: wb.Union(*two(rng))
    cases["intersection"] = lambda rng: wb.Intersection(*two(rng))
    cases["difference"] = lambda rng: wb.Difference(*two(rng))
    cases["smooth_blend"] = lambda rng: wb.SmoothBlend(*two(rng), k=3.0)
    cases["wide_union"] = lambda rng: wb.Union(
        *[make_primitive(k, rng, rng.uniform(-2, 2, size=3), 0.7) for k in PRIMITIVE_KINDS]
    )
    cases["wide_blend"] = lambda rng: wb.Blend(
        *[make_primitive(k, rng, rng.uniform(-2, 2, size=3), 0.7) for k in PRIMITIVE_KINDS]
    )
    cases["twist"] = lambda rng: wb.Twist(wb.Box((0.3, 0, 0), (0.5, 0.1, 0.8), 0.3), (0.2, 0.1, 1.0), 1.4)
    cases["taper"] = lambda rng: wb.Taper(wb.Box((0, 0.2, 0), (0.4, 0.3, 0.8), 0.3), (0.0, 0.2, 1.0), -0.5)
    cases["twist_off_axis"] = lambda rng: wb.Twist(wb.Segment((0.8, 0.3, -0.6), (1.2, -0.2, 0.9), 0.4), (0, 0, 1), -2.0)
    cases["taper_off_axis"] = lambda rng: wb.Taper(wb.Box((0.9, 0.5, 0.6), (0.3, 0.2, 0.5), 0.3), (0.0, 0.0, 1.0), 0.7)
    cases["bend_off_axis"] = lambda rng: wb.Bend(wb.Box((0.3, -0.6, 0.3), (0.8, 0.2, 0.3), 0.3), (1, 0, 0), (0, 1, 0), 0.6)
    cases["bend"] = lambda rng: wb.Bend(wb.Cylinder((-1.2, 0, 0), (1.2, 0, 0), 0.2, 0.4), (1, 0, 0), (0, 1, 0), 0.8)
    cases["bend_negative"] = lambda rng: wb.Bend(wb.Segment((-1, 0, 0.2), (1, 0.1, 0), 0.4), (1, 0, 0), (0, 0, 1), -0.9)
    cases["transform"] = lambda rng: make_primitive("cone", rng).rotate((1, 2, 3), 0.7).scale((0.5, 1.7, 1.0)).translate(
        (3.0, -1.0, 0.5)
    )
    cases["nested"] = lambda rng: wb.Twist(
        wb.Bend(make_primitive("sweep", rng) - make_primitive("point", rng), (0, 0, 1), (1, 0, 0), 0.4), (1, 0, 0), 0.9
    ).rotate((0, 1, 0), 0.4)
    return cases


BOUNDS_CASES = _bounds_cases()


@pytest.mark.parametrize("case", sorted(BOUNDS_CASES))
def test_field_is_zero_outside_bounds(case, device):
    rng = np.random.default_rng(21)
    model = BOUNDS_CASES[case](rng)
    lo, hi = model.bounds()
    assert np.all(np.isfinite(lo)) and np.all(lo < hi)
    pts = _outside_points(model, rng)
    assert len(pts) > 1000
    values = wb.field(model, pts, device=device)
    bad = values != 0.0
    assert not np.any(bad), f"{int(bad.sum())} points outside bounds() have F != 0, e.g. {pts[bad][0].tolist()} -> {values[bad][0]}"
    ref = reference_field(model, pts.astype(np.float64))
    assert np.all(ref == 0.0), f"reference F != 0 outside bounds() at {pts[ref != 0.0][0].tolist()}"
    # and the box is not vacuous: the field is non-zero somewhere inside
    inside = (lo + (hi - lo) * rng.random((4000, 3))).astype(np.float32)
    assert np.any(wb.field(model, inside, device=device) > 0.0)


def test_disjoint_intersection_has_empty_bounds_and_zero_field(device):
    model = wb.Point((0, 0, 0), 1.0) & wb.Point((5, 0, 0), 1.0)
    lo, hi = model.bounds()
    assert np.any(lo > hi)
    pts = np.random.default_rng(0).uniform(-2, 7, size=(2000, 3))
    assert np.all(wb.field(model, pts, device=device) == 0.0)
