"""polygonize at its boundary: bad arguments are refused naming the value, pointless ones warn."""

import warnings

import numpy as np
import pytest

import warpblob as wb

BALL = wb.Point((0, 0, 0), 1.0)  # field at most 1, box [-1, 1]^3 (and a little)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "x", None, True])
def test_cellsize_must_be_a_finite_positive_number(bad):
    with pytest.raises(wb.WarpblobError, match=f"cellsize.*{bad!r}"):
        wb.polygonize(BALL, cellsize=bad)


@pytest.mark.parametrize("bad", [0, -0.5, float("nan"), float("inf"), "0.5", None, False])
def test_iso_must_be_a_finite_positive_number(bad):
    # at iso <= 0 all of space outside the model (F = 0) would count as inside
    with pytest.raises(wb.WarpblobError, match=f"iso.*{bad!r}"):
        wb.polygonize(BALL, cellsize=0.2, iso=bad)


@pytest.mark.parametrize("bad", [0.0, -1e-4, float("nan"), "tight", 0.5, 0.7])
def test_tolerance_must_be_positive_and_below_iso(bad):
    with pytest.raises(wb.WarpblobError, match=f"tolerance.*{bad!r}"):
        wb.polygonize(BALL, cellsize=0.2, tolerance=bad)


@pytest.mark.parametrize("bad", [0, -1, float("nan"), float("inf"), "1GB", True])
def test_max_memory_must_be_a_positive_number(bad):
    with pytest.raises(wb.WarpblobError, match=f"max_memory.*{bad!r}"):
        wb.polygonize(BALL, cellsize=0.2, max_memory=bad)


def test_a_tiny_memory_limit_is_a_resource_error_naming_the_stage():
    # the limit is shown in a unit that keeps its value: "10 B", not "0.0 MiB"
    with pytest.raises(wb.ResourceError, match=r"block classification.*more than the 10 B available"):
        wb.polygonize(BALL, cellsize=0.2, max_memory=10)


@pytest.mark.parametrize(
    "n, text", [(0, "0 B"), (1023, "1023 B"), (1024, "1.0 KiB"), (3 * 2**20 + 2**19, "3.5 MiB"), (5 * 2**30, "5.0 GiB")]
)
def test_byte_counts_are_shown_in_a_unit_that_keeps_their_value(n, text):
    from warpblob._stages import format_bytes

    assert format_bytes(n) == text


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True])
def test_threads_must_be_a_positive_integer(bad):
    with pytest.raises(wb.WarpblobError, match=f"threads.*{bad!r}"):
        wb.polygonize(BALL, cellsize=0.2, threads=bad)


@pytest.mark.parametrize(
    "bad",
    [
        ((0, 0, 0), (0, 1, 1)),  # empty along x
        ((1, 1, 1), (0, 0, 0)),  # upper below lower
        ((0, 0, 0), (1, 1)),  # wrong shape
        ((0, 0, 0), (1, 1, 1), (2, 2, 2)),
        ((0, 0, float("nan")), (1, 1, 1)),
        ((0, 0, 0), (1, 1, float("inf"))),
        "box",
    ],
)
def test_bounds_must_be_two_finite_ordered_points(bad):
    with pytest.raises(wb.WarpblobError, match="bounds"):
        wb.polygonize(BALL, cellsize=0.2, bounds=bad)


@pytest.mark.parametrize("option, bad", [("relax", "yes"), ("relax", None), ("progress", "auto")])
def test_flags_must_be_booleans(option, bad):
    with pytest.raises(wb.WarpblobError, match=f"{option}.*{bad!r}"):
        wb.polygonize(BALL, cellsize=0.2, **{option: bad})


def test_iso_above_the_fields_bound_warns_that_the_mesh_is_empty():
    # a lone Wyvill primitive's field never exceeds 1
    with pytest.warns(UserWarning, match=r"iso=2\.0 is above the field's upper bound"):
        mesh = wb.polygonize(BALL, cellsize=0.2, iso=2.0)
    assert mesh.face_count == 0


def test_blends_sum_above_one_so_a_higher_iso_is_valid():
    # two coincident points blend to a field of 2 at the centre: iso = 1.5 has a surface
    model = wb.Blend(wb.Point((0, 0, 0), 1.0), wb.Point((0, 0, 0), 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = wb.polygonize(model, cellsize=0.1, iso=1.5)
    assert mesh.is_closed_manifold()
    # 2 g(x) = 1.5 at the sphere's normalized radius x = sqrt(1 - 0.75^(1/3))
    r = np.sqrt(1.0 - 0.75 ** (1.0 / 3.0))
    assert np.abs(np.linalg.norm(mesh.vertices, axis=1) - r).max() < 1e-3


def test_a_cell_larger_than_the_model_warns_naming_cellsize_and_box():
    with pytest.warns(UserWarning, match=r"cellsize=5\.0 is larger than the model box's smallest side .*box \[-1"):
        mesh = wb.polygonize(BALL, cellsize=5.0)
    assert mesh.face_count == 0


def test_an_empty_mesh_from_a_nonempty_model_warns():
    # h = 1.2 is under the box's side (2), but no grid vertex comes within the
    # sphere's radius 0.454 of the centre, so no edge crosses the surface
    with pytest.warns(UserWarning, match=r"the mesh is empty: no grid edge of cellsize=1\.2 crosses"):
        mesh = wb.polygonize(BALL, cellsize=1.2)
    assert mesh.face_count == 0


def test_a_clipped_box_off_the_model_is_empty_without_a_warning():
    # bounds chosen by the caller: an empty result is theirs to expect
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = wb.polygonize(BALL, cellsize=0.1, bounds=((5, 5, 5), (6, 6, 6)))
    assert mesh.face_count == 0


def test_inputs_are_not_modified():
    lower, upper = np.array([-2.0, -2.0, -2.0]), np.array([2.0, 2.0, 2.0])
    wb.polygonize(BALL, cellsize=0.2, bounds=(lower, upper))
    np.testing.assert_array_equal(lower, [-2.0, -2.0, -2.0])
    np.testing.assert_array_equal(upper, [2.0, 2.0, 2.0])
