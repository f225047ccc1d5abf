"""The reference models of warpblob.scenes: tree statistics, bounds, non-emptiness, layout."""

import numpy as np
import pytest

import warpblob as wb
from warpblob import scenes

#: name -> (primitives, operators incl. warps and transform nodes, depth)
EXPECTED = {
    "peanut": (2, 1, 2),
    "tumor": (10, 1, 2),
    "eggshell": (2, 1, 2),
    "cake": (6, 1, 2),
    "three_slabs": (3, 1, 2),
    "mug": (3, 3, 3),
    "towers": (7296, 7360, 64),
    "medusa": (2920, 11, 6),
    "head": (44, 13, 4),
}


@pytest.fixture(scope="module")
def models():
    """One instance of every scene, built once for the module."""
    return {name: fn() for name, fn in scenes.ALL.items()}


def _grid(lower, upper, n=20):
    axes = [np.linspace(lower[i], upper[i], n) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def test_all_lists_every_scene_in_order():
    assert list(scenes.ALL) == [
        "peanut", "tumor", "eggshell", "cake", "three_slabs", "mug", "towers", "medusa", "head",
    ]
    assert "3slabs" not in scenes.ALL
    for name, fn in scenes.ALL.items():
        assert fn is getattr(scenes, name)
        assert name in scenes.__all__
        assert fn.__doc__ and ">>>" in fn.__doc__


def test_default_is_tumor():
    m = scenes.default()
    assert isinstance(m, wb.Blend)
    assert (m.primitive_count(), m.operator_count(), m.depth()) == EXPECTED["tumor"]


@pytest.mark.parametrize("name", list(EXPECTED))
def test_counts_and_depth(models, name):
    m = models[name]
    assert (m.primitive_count(), m.operator_count(), m.depth()) == EXPECTED[name]


@pytest.mark.parametrize("name", list(EXPECTED))
def test_linearized_counts_match(models, name):
    lm = wb.linearize(models[name])
    assert (lm.primitive_count, lm.operator_count, lm.depth) == EXPECTED[name]


@pytest.mark.parametrize("name", list(EXPECTED))
def test_bounds_finite_and_non_empty(models, name):
    lower, upper = models[name].bounds()
    assert lower.shape == upper.shape == (3,)
    assert np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))
    assert np.all(upper - lower > 0.5)
    limit = 8.0 if name == "towers" else 3.5
    assert np.all(np.abs(lower) <= limit) and np.all(np.abs(upper) <= limit)


@pytest.mark.parametrize("name", list(EXPECTED))
def test_model_has_inside_and_outside(models, name):
    m = models[name]
    values = wb.field(m, _grid(*m.bounds()))
    assert np.all(np.isfinite(values))
    assert np.any(values >= wb.ISO_VALUE)
    assert np.any(values < wb.ISO_VALUE)


@pytest.mark.parametrize("name", list(EXPECTED))
def test_each_call_returns_a_fresh_model(name):
    fn = scenes.ALL[name]
    a, b = fn(), fn()
    assert a is not b
    if name != "towers":  # walking 14k nodes twice is fine but slow-ish; the others suffice
        ids_a = {id(n) for n in a.walk()}
        assert not ids_a & {id(n) for n in b.walk()}


# --- model-specific layout -------------------------------------------------


def test_peanut_is_connected_with_a_waist():
    m = scenes.peanut()
    f = wb.field(m, [[0.0, 0.0, 0.0], [-0.45, 0.0, 0.0], [0.45, 0.0, 0.0], [0.0, 0.45, 0.0], [-0.45, 0.45, 0.0]])
    assert np.all(f[:3] >= 0.5)  # both lobes and the neck between them
    assert f[3] < 0.5 <= f[4]  # narrower at the waist than over a lobe


def test_tumor_is_one_blend_of_ten_points():
    m = scenes.tumor()
    assert type(m) is wb.Blend and len(m.children) == 10
    assert all(type(c) is wb.Point for c in m.children)
    centres = [tuple(c.center) for c in scenes.tumor().children]
    assert centres == [tuple(c.center) for c in m.children]  # fixed literals, not random


def test_eggshell_is_a_thin_hollow_shell():
    m = scenes.eggshell()
    assert type(m) is wb.Difference
    r = np.linspace(0.0, 2.0, 401)
    inside = wb.field(m, np.stack([r, np.zeros_like(r), np.zeros_like(r)], axis=1)) >= 0.5
    shell = r[inside]
    assert not inside[0]  # hollow at the centre
    assert 0.05 < shell.max() - shell.min() < 0.4  # one thin wall
    assert np.all(np.diff(np.flatnonzero(inside)) == 1)


def test_cake_has_three_tiers_above_the_ground():
    m = scenes.cake()
    assert m.bounds()[0][2] >= 0.0
    # radius of the solid at the middle height of each tier shrinks upwards
    widths = []
    for z in (0.85, 1.72, 2.55):
        x = np.linspace(0.0, 3.0, 601)
        inside = wb.field(m, np.stack([x, np.zeros_like(x), np.full_like(x, z)], axis=1)) >= 0.5
        assert inside[0]
        widths.append(x[inside].max())
    assert widths[0] > widths[1] + 0.4 > widths[2] + 0.8


def test_three_slabs_colours_and_contact():
    m = scenes.three_slabs()
    assert [type(c) for c in m.children] == [wb.Box] * 3
    cols = wb.color(m, [[-1.2, 0.0, 0.0], [0.0, 0.0, 0.0], [1.2, 0.0, 0.0]])
    green = cols[0]
    assert green[1] > 0.6 and green[0] < 0.4 and green[2] < 0.4
    assert len({tuple(np.round(c, 3)) for c in cols}) == 3
    # the slabs touch: solid all along the x axis from the first to the last
    x = np.linspace(-1.2, 1.2, 241)
    assert np.all(wb.field(m, np.stack([x, np.zeros_like(x), np.zeros_like(x)], axis=1)) >= 0.5)


def test_mug_is_hollow_with_closed_bottom_and_handle():
    m = scenes.mug()
    f = wb.field(m, [
        [0.0, 0.0, 1.5],  # inside the cup: empty
        [0.0, 0.0, 0.4],  # bottom: solid
        [1.15, 0.0, 1.5],  # wall: solid
        [1.72, 0.0, 1.4 + 0.62],  # top of the handle ring
        [1.72, 0.0, 1.15],  # hole of the handle (off its axis): empty
    ])
    assert f[0] < 0.5 <= f[1]
    assert f[2] >= 0.5 and f[3] >= 0.5 and f[4] < 0.5


def test_towers_structure():
    m = scenes.towers()
    assert isinstance(m, wb.Transform)
    grid = m.child
    towers, stack = [], [grid]
    while stack:
        n = stack.pop()
        if isinstance(n, wb.Transform):
            towers.append(n)
        else:
            assert type(n) is wb.Union and len(n.children) == 2
            stack.extend(n.children)
    assert len(towers) == 64
    tower = towers[0].child
    chain = 0
    while type(tower) is wb.Union:
        floor, tower = tower.children
        assert type(floor) is wb.Blend and len(floor.children) == 2
        chain += 1
    assert chain == 56 and type(tower) is wb.Blend
    lower, upper = m.bounds()
    assert lower[2] >= 0.0 and upper[2] < 8.0
    np.testing.assert_allclose(lower[:2], -upper[:2], atol=1e-9)  # centred


def test_medusa_structure():
    m = scenes.medusa()
    assert not any(isinstance(n, wb.Transform) for n in m.walk())
    assert type(m) is wb.Union
    diff, hair = m.children
    assert type(diff) is wb.Difference and type(hair) is wb.Blend
    face, eyes = diff.children
    assert type(face) is wb.Blend and type(eyes) is wb.Union and len(eyes.children) == 2
    assert 20 <= len(face.children) <= 60
    g1, g2 = hair.children
    assert type(g1) is wb.Union and type(g2) is wb.Union
    (smooth,) = g1.children
    assert type(smooth) is wb.SmoothBlend
    snakes = [*smooth.children, *g2.children]
    assert [type(s) for s in snakes] == [wb.Blend] * 3
    assert all(len(s.children) >= 900 for s in snakes)
    assert all(not c.children for s in snakes for c in s.children)
    # the eyes carve sockets into the face
    assert wb.field(m, [[0.32, -0.88, 0.88]])[0] < 0.5


def test_head_layers_are_nested_in_order():
    m = scenes.head()
    assert type(m) is wb.Union and len(m.children) == 4
    assert all(type(c) is wb.Difference for c in m.children)
    layer_colors = [np.asarray(c.children[0].children[0].color) for c in m.children]
    for direction in ((0, 1, 0), (0, -1, 0), (1, 0, 0), (0, 0, 1), (0, 0, -1)):
        t = np.linspace(0.0, 3.2, 3201)
        pts = np.array([0.0, 0.0, 0.4]) + np.outer(t, direction)
        inside = wb.field(m, pts) >= 0.5
        outer_edges = np.flatnonzero(inside[:-1] & ~inside[1:])  # last inside sample of each interval
        assert len(outer_edges) == 4, direction  # skull, CSF, grey, white: separated by gaps
        # colour just inside each interval's outer surface, from the outside in
        cols = wb.color(m, pts[outer_edges[::-1] - 2])
        np.testing.assert_allclose(cols, np.array(layer_colors), atol=1e-3)
