"""Bad input to the field API is refused at the boundary, naming the value and its index.

NaN and infinite coordinates used to evaluate to F = 0, and a coordinate
beyond float32's range turned into inf before any check saw it; ``threads=0``
was accepted. Every check here is against the value the test passed.
"""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import warpblob as wb
from warpblob.field import bound_balls, bound_blocks, grid_field

MODEL = wb.Point((0, 0, 0), 1.0)
POINT_FUNCTIONS = [wb.field, wb.gradient, wb.color, wb.evaluate]


def _points_with(value, row=3, column=1, n=6):
    pts = np.zeros((n, 3))
    pts[:, 0] = np.linspace(-0.5, 0.5, n)
    pts[row, column] = value
    return pts


def test_model_error_is_a_warpblob_value_error():
    assert issubclass(wb.ModelError, wb.WarpblobError) and issubclass(wb.ModelError, ValueError)


@pytest.mark.parametrize("fn", POINT_FUNCTIONS, ids=lambda f: f.__name__)
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_nonfinite_numpy_points_are_refused(fn, value, device):
    pts = _points_with(value)
    before = pts.copy()
    with pytest.raises(wb.ModelError, match=rf"points: row 3 is \[.*{value}.*\]"):
        fn(MODEL, pts, device=device)
    np.testing.assert_array_equal(pts, before)  # inputs are never modified


@pytest.mark.parametrize("fn", POINT_FUNCTIONS, ids=lambda f: f.__name__)
@pytest.mark.parametrize("layout", ["vec3", "float32"])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_nonfinite_warp_points_are_refused(fn, layout, value, device):
    host = _points_with(value).astype(np.float32)
    arr = wp.array(host, dtype=wp.vec3 if layout == "vec3" else wp.float32, device=device)
    with pytest.raises(wb.ModelError, match=rf"points: row 3 is \[.*{value}.*\]"):
        fn(MODEL, arr)
    np.testing.assert_array_equal(arr.numpy().reshape(-1, 3), host)


def test_the_first_bad_row_of_a_warp_array_is_named(device):
    # many threads flag rows at once: the smallest index must win
    host = np.zeros((200_000, 3), dtype=np.float32)
    for row in (123_457, 150_000, 199_999):
        host[row, 2] = np.nan
    with pytest.raises(wb.ModelError, match="row 123457 "):
        wb.field(MODEL, wp.array(host, dtype=wp.vec3, device=device))


def test_a_point_beyond_float32_reports_the_value_passed(device):
    pts = [[0.0, 0.0, 0.0], [1e39, 0.0, 0.0]]
    with pytest.raises(wb.ModelError, match=r"row 1 is \[1e\+39, 0\.0, 0\.0\]"):
        wb.field(MODEL, pts, device=device)
    with pytest.raises(wb.ModelError, match=r"row 0 is \[-1e\+300, 1\.0, 2\.0\]"):
        wb.field(MODEL, np.array([[-1e300, 1.0, 2.0]]), device=device)
    # the largest float32 itself is a valid (far away) point
    big = float(np.finfo(np.float32).max)
    assert wb.field(MODEL, [[big, 0.0, 0.0]], device=device).tolist() == [0.0]


def test_an_entry_that_is_not_a_number_is_named():
    with pytest.raises(wb.ModelError, match=r"'x' at index \[1, 2\]"):
        wb.field(MODEL, [[0.0, 0.0, 0.0], [1.0, 2.0, "x"]])
    with pytest.raises(wb.ModelError, match=r"at index \[0, 0\]"):
        wb.field(MODEL, [[10**400, 0.0, 0.0]])


@pytest.mark.parametrize("layout", ["numpy", "warp"])
def test_bad_ball_centres_and_radii_are_refused(layout, device):
    centers = np.zeros((5, 3), dtype=np.float32)
    radii = np.full(5, 0.1, dtype=np.float32)

    def put(a, dtype):
        return a if layout == "numpy" else wp.array(a, dtype=dtype, device=device)

    bad = centers.copy()
    bad[2, 0] = np.nan
    with pytest.raises(wb.ModelError, match=r"centers: row 2 is \[nan, 0\.0, 0\.0\]"):
        bound_balls(MODEL, put(bad, wp.vec3), put(radii, wp.float32), device=device)
    for value in (-0.5, np.nan, np.inf):
        r = radii.copy()
        r[4] = value
        with pytest.raises(wb.ModelError, match=rf"radii: entry 4 is {value}; radii must be finite"):
            bound_balls(MODEL, put(centers, wp.vec3), put(r, wp.float32), device=device)
    # a ball of radius 0 is a point: its bounds hold the point's value
    r = radii.copy()
    r[0] = 0.0
    b = bound_balls(MODEL, put(centers, wp.vec3), put(r, wp.float32), device=device)
    b = b if layout == "numpy" else b.numpy().reshape(-1, 2)
    assert b[0, 0] <= 1.0 <= b[0, 1]


def test_radii_of_the_wrong_shape_or_type_are_refused(device):
    with pytest.raises(wb.ModelError, match=r"radii: expected shape \(N,\)"):
        bound_balls(MODEL, np.zeros((2, 3)), np.ones((2, 1)), device=device)
    with pytest.raises(wb.ModelError, match="radii: expected a 1-D Warp float32 array"):
        bound_balls(MODEL, np.zeros((2, 3)), wp.ones(2, dtype=wp.float64, device=device), device=device)


def test_bad_grid_frames_are_refused():
    for origin, h, shape, message in [
        ((1e39, 0, 0), 0.1, (2, 2, 2), r"origin must be finite .* got \[1e\+39, 0\.0, 0\.0\]"),
        ((0, np.nan, 0), 0.1, (2, 2, 2), r"origin must be finite .* got \[0\.0, nan, 0\.0\]"),
        ((0, 0, 0), np.inf, (2, 2, 2), "cellsize must be > 0 .* got inf"),
        ((0, 0, 0), 1e39, (2, 2, 2), "cellsize must be > 0 .* got 1e[+]39"),
        ((0, 0, 0), np.nan, (2, 2, 2), "cellsize must be > 0 .* got nan"),
        ((0, 0, 0), 0.1, (2.5, 2, 2), r"shape must be 3 integers >= 1, got \(2\.5, 2, 2\)"),
        ((0, 0, 0), 1e37, (100, 2, 2), r"shape reach grid index \[100, 2, 2\]"),
        ((0, 0, 0), 1e-3, (2**31, 1, 1), r"shape reach grid index \[2147483648, 1, 1\]"),
    ]:
        with pytest.raises(wb.ModelError, match="grid_field: " + message):
            grid_field(MODEL, origin, h, shape)
    # numpy integers are integers
    assert grid_field(MODEL, (-1, -1, -1), 0.5, np.array([5, 5, 5])).shape == (5, 5, 5)


def test_bad_block_frames_are_refused():
    with pytest.raises(wb.ModelError, match=r"bound_blocks: origin must be finite .* \[inf, 0\.0, 0\.0\]"):
        bound_blocks(MODEL, (np.inf, 0, 0), 0.1, [[0, 0, 0]])
    with pytest.raises(wb.ModelError, match=r"bound_blocks: blocks reach grid index \[2147483656, 8, 8\]"):
        bound_blocks(MODEL, (0, 0, 0), 1e-9, [[0, -1, -1], [2**28, 0, 0]])


FUNCTIONS_WITH_THREADS = {
    "field": lambda t: wb.field(MODEL, [[0.0, 0.0, 0.0]], threads=t),
    "gradient": lambda t: wb.gradient(MODEL, [[0.0, 0.0, 0.0]], threads=t),
    "color": lambda t: wb.color(MODEL, [[0.0, 0.0, 0.0]], threads=t),
    "evaluate": lambda t: wb.evaluate(MODEL, [[0.0, 0.0, 0.0]], threads=t),
    "bound_balls": lambda t: bound_balls(MODEL, np.zeros((1, 3)), [0.1], threads=t),
    "bound_blocks": lambda t: bound_blocks(MODEL, (-0.8, -0.8, -0.8), 0.2, [[0, 0, 0]], threads=t),
    "grid_field": lambda t: grid_field(MODEL, (-1, -1, -1), 0.5, (3, 3, 3), threads=t),
}


@pytest.mark.parametrize("name", sorted(FUNCTIONS_WITH_THREADS))
def test_threads_must_be_a_positive_integer(name):
    call = FUNCTIONS_WITH_THREADS[name]
    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises(wb.WarpblobError, match=f"threads must be a positive integer or None, got {bad!r}"):
            call(bad)
    call(np.int64(2))
    call(None)
