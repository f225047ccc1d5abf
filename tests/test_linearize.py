"""The linearized form: counts, operand order, register bound, links and grids."""

import numpy as np
import pytest

import warpblob as wb
from warpblob import _linearize
from warpblob.tree import _kinds


def balanced_differences(levels, offset=0.0):
    """A perfectly balanced binary tree of Differences (never merged) of 2**levels points."""
    if levels == 0:
        return wb.Point((offset, 0, 0), 1.0)
    return wb.Difference(balanced_differences(levels - 1, offset), balanced_differences(levels - 1, offset + 0.1))


def test_counts_and_depth():
    m = wb.Union(wb.Point((0, 0, 0), 1.0), wb.Blend(wb.Point((1, 0, 0), 1.0), wb.Segment((0, 0, 0), (0, 1, 0), 0.5)))
    lm = wb.linearize(m.translate((1, 2, 3)))
    assert (lm.primitive_count, lm.operator_count, lm.depth) == (3, 3, 3)
    assert lm.node_count == 5  # the transform is folded into the leaves
    assert lm.nbytes == sum(a.nbytes for a in lm._arrays().values())


def test_registers_chain_and_balanced():
    chain = wb.Point((0, 0, 0), 1.0)
    for k in range(40):
        chain = wb.Difference(chain, wb.Point((0.05 * k, 0, 0), 0.3))
    assert wb.linearize(chain).registers == 1
    # the deep operand is evaluated first even when the user wrote it second
    flipped = wb.Point((0, 0, 0), 1.0)
    for k in range(40):
        flipped = wb.Difference(wb.Point((0.05 * k, 0, 0), 0.3), flipped)
    assert wb.linearize(flipped).registers == 1
    for levels in (1, 3, 5):
        assert wb.linearize(balanced_differences(levels)).registers == levels


def test_reordered_operands_keep_the_field():
    m = wb.Difference(wb.Point((0, 0, 0), 1.0), balanced_differences(3, 0.2))
    lm = wb.linearize(m)
    root_params = lm.params[0]
    assert root_params[0] == 1.0  # stored as (b, a)
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, (2000, 3))
    a = wb.field(wb.Point((0, 0, 0), 1.0), pts)
    b = wb.field(balanced_differences(3, 0.2), pts)
    np.testing.assert_allclose(wb.field(m, pts), np.minimum(a, 1.0 - np.minimum(b, 1.0)), atol=1e-6)


def test_too_many_registers_raise(monkeypatch):
    monkeypatch.setattr(_linearize, "SLOTS", 2)
    with pytest.raises(wb.ModelError, match="3 registers"):
        wb.linearize(balanced_differences(3))


def test_too_deep_warp_nesting_raises():
    m = wb.Point((0, 0, 0), 1.0)
    for _ in range(_linearize.WARP_NESTING + 1):
        m = wb.Twist(m, (0, 0, 1), 0.1)
    with pytest.raises(wb.ModelError, match="nested 9 deep"):
        wb.linearize(m)


def test_same_kind_operators_merge():
    pts = [wb.Point((0.3 * k, 0, 0), 0.5) for k in range(5)]
    nested = wb.Union(pts[0], wb.Union(pts[1], wb.Union(pts[2], wb.Union(pts[3], pts[4]))))
    lm = wb.linearize(nested)
    assert lm.node_count == 6 and lm.evaluation_depth == 2 and lm.depth == 5


def test_unions_and_intersections_of_one_operand_vanish():
    """Union(a) and Intersection(a) are a, exactly: they leave the evaluation
    tree (medusa has two such unions); a blend of one is kept (its colour is
    its operand's divided by its own value, which rounds)."""
    a = wb.Blend(wb.Point((0, 0, 0), 1.0), wb.Segment((0, 0, 0), (1, 0, 0), 0.5))
    for wrapped in (wb.Union(a), wb.Intersection(wb.Union(a)), wb.Union(wb.Intersection(a)).translate((0.2, 0, 0))):
        lm = wb.linearize(wrapped)
        assert lm.node_count == 3 and lm.kind[0] == _kinds.BLEND
    pts = np.random.default_rng(1).uniform(-1.5, 2.0, (2000, 3)).astype(np.float32)
    for x, y in zip(wb.evaluate(wb.Union(a), pts), wb.evaluate(a, pts)):
        assert np.array_equal(x, y)
    assert wb.linearize(wb.Blend(a)).node_count == 3  # Blend(Blend(...)) merges; a lone Blend(point) stays
    assert wb.linearize(wb.Blend(wb.Point((0, 0, 0), 1.0))).node_count == 2


def test_links_are_consistent():
    lm = wb.linearize(wb.scenes.head())
    n = lm.node_count
    assert lm.parent[0] == -1 and lm.skip[0] == n
    for i in range(1, n):
        p = lm.parent[i]
        assert p < i < lm.skip[i] <= lm.skip[p]  # pre-order: a subtree is a contiguous range
    leaves = lm.kind < _kinds.PRIMITIVE_KIND_END
    assert np.all(lm.skip[leaves] == np.nonzero(leaves)[0] + 1)
    assert np.all(lm.ref[leaves] >= 0)


def test_grid_lists_every_operand_whose_box_holds_the_point():
    rng = np.random.default_rng(3)
    kids = [wb.Point(rng.uniform(-2, 2, 3), rng.uniform(0.2, 0.6)) for _ in range(200)]
    lm = wb.linearize(wb.Blend(*kids))
    assert lm.ref[0] == 0 and lm.grid_dims.shape == (1, 3)
    dims = lm.grid_dims[0]
    pts = rng.uniform(lm.lower[0], lm.upper[0], (3000, 3))
    cell = np.clip(np.floor((pts - lm.grid_lower[0]) * lm.grid_inv_cell[0]).astype(int), 0, dims - 1)
    flat = lm.grid_base[0] + (cell[:, 2] * dims[1] + cell[:, 1]) * dims[0] + cell[:, 0]
    children = np.nonzero(lm.parent == 0)[0]
    for p, c in zip(pts, flat):
        listed = lm.cell_items[lm.cell_offsets[c] : lm.cell_offsets[c + 1]]
        assert np.all(np.diff(listed) > 0)  # ascending: the full traversal's order
        holds = children[np.all((lm.lower[children] <= p) & (p <= lm.upper[children]), axis=1)]
        assert set(holds) <= set(listed)


def test_linearize_rejects_non_models():
    with pytest.raises(wb.ModelError, match="str"):
        wb.linearize("tumor")


def test_grids_of_several_wide_operators_share_the_cell_arrays():
    """Each wide operator's cells index its own run of ``cell_items`` (the runs
    follow each other), and list only its own operands, in ascending order,
    including every operand whose box holds a point of the cell."""
    rng = np.random.default_rng(8)
    groups = [
        wb.Blend(*[wb.Point(rng.uniform(-1, 1, 3) + 3.0 * g, rng.uniform(0.2, 0.5)) for _ in range(8 + 3 * g)])
        for g in range(6)
    ]
    lm = wb.linearize(wb.Union(*groups, *[wb.Point((9.0, k, 0.0), 0.3) for k in range(3)]))
    wide = np.nonzero(lm.ref >= 0)[0]
    wide = wide[lm.kind[wide] >= _kinds.PRIMITIVE_KIND_END]
    assert len(wide) == 7  # the union (9 operands) and its 6 blends
    end = 0
    for g in range(len(lm.grid_base)):
        base, cells = lm.grid_base[g], int(np.prod(lm.grid_dims[g]))
        assert lm.cell_offsets[base] == end  # this grid's items start where the last grid's ended
        end = lm.cell_offsets[base + cells]
        if g + 1 < len(lm.grid_base):
            assert lm.grid_base[g + 1] == base + cells + 1
    assert end == len(lm.cell_items)
    for node in wide:
        g = lm.ref[node]
        dims = lm.grid_dims[g]
        children = np.nonzero(lm.parent == node)[0]
        pts = rng.uniform(lm.lower[node], lm.upper[node], (500, 3))
        cell = np.clip(np.floor((pts - lm.grid_lower[g]) * lm.grid_inv_cell[g]).astype(int), 0, dims - 1)
        flat = lm.grid_base[g] + (cell[:, 2] * dims[1] + cell[:, 1]) * dims[0] + cell[:, 0]
        for p, c in zip(pts, flat):
            listed = lm.cell_items[lm.cell_offsets[c] : lm.cell_offsets[c + 1]]
            assert np.all(np.diff(listed) > 0) and set(listed) <= set(children)
            holds = children[np.all((lm.lower[children] <= p) & (p <= lm.upper[children]), axis=1)]
            assert set(holds) <= set(listed)
