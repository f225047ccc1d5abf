"""Interval bounds of the field over balls: every sampled point lies within them."""

import numpy as np
import pytest

import warpblob as wb
from reference import reference_evaluate
from warpblob.field import bound_balls, bound_blocks


def _ball_samples(rng, centers, radii, per_ball):
    d = rng.normal(size=(len(centers), per_ball, 3))
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    s = radii[:, None, None] * rng.uniform(0, 1, (len(centers), per_ball, 1)) ** (1 / 3)
    return centers[:, None, :] + d * s


MODELS = {
    "tumor": wb.scenes.tumor,
    "mug": wb.scenes.mug,
    "head": wb.scenes.head,
    "medusa": wb.scenes.medusa,
    "mixed": lambda: wb.SmoothBlend(
        wb.Cone((0, 0, 0), (0, 0, 1), 0.4, 0.1, 0.3).scale((1, 2, 0.5)),
        wb.Polygon([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0.5, 0.3, 0], [0, 1, 0]], 0.3),
        k=3.0,
    )
    - wb.Ring((0.5, 0.5, 0), (0, 1, 0), 0.4, 0.2)
    & wb.Box((0.3, 0.3, 0.3), (0.8, 0.8, 0.8), 0.2),
}


def _sub_block_balls(origin, h, blocks):
    """Centres (N, 64, 3) and radius of the sub-block balls of ``bound_blocks``,
    in float32 as the kernel computes them."""
    s = np.arange(4)
    sk, sj, si = np.meshgrid(s, s, s, indexing="ij")
    local = np.stack([si, sj, sk], axis=-1).reshape(64, 3)
    index = (8 * blocks[:, None, :] + 2 * local[None] + 1).astype(np.float32)
    h = np.float32(h)
    return origin.astype(np.float32) + h * index, h * np.float32(1.7320509) * np.float32(1.0001)


@pytest.mark.parametrize("name", sorted(MODELS) + ["random-0", "random-3"])
def test_block_bounds_hold_and_match_ball_bounds(name, device):
    """One tree walk per block (bounds rows) bounds its 64 sub-blocks: every
    sampled point of a sub-block ball lies within them, and they equal the
    per-ball bounds up to the rounding of sums taken in another order."""
    if name.startswith("random"):
        from test_field import random_model

        model = random_model(int(name.split("-")[1]))
    else:
        model = MODELS[name]()
    rng = np.random.default_rng(11)
    lo, hi = (np.asarray(b, dtype=np.float64) for b in model.bounds())
    lo, hi = np.maximum(lo, -3.0), np.minimum(hi, 3.0)  # warp boxes are far larger than their parts
    h = float(np.min(hi - lo)) / 23.0
    origin = (lo - 0.37 * h).astype(np.float32)  # blocks not aligned with the model box
    nb = np.ceil((hi - origin) / (8 * h)).astype(int)
    blocks = np.stack(np.meshgrid(*[np.arange(n) for n in nb], indexing="ij"), axis=-1).reshape(-1, 3)
    bounds = bound_blocks(model, origin, h, blocks, device=device)
    centers, radius = _sub_block_balls(origin, h, blocks)
    centers, bounds = centers.reshape(-1, 3), bounds.reshape(-1, 2)
    pts = _ball_samples(rng, centers.astype(np.float64), np.full(len(centers), radius, np.float64), 6)
    f = reference_evaluate(model, pts.reshape(-1, 3))[0].reshape(len(centers), -1)
    assert np.all(f >= bounds[:, :1] - 2e-6), "a sampled point lies below its sub-block's F_min"
    assert np.all(f <= bounds[:, 1:] + 2e-6), "a sampled point lies above its sub-block's F_max"
    balls = bound_balls(model, centers, np.full(len(centers), radius), device=device)
    known = balls < 1e29  # a warp's unknown bound [0, inf) is 1e30 plus the rest
    np.testing.assert_array_equal(known, bounds < 1e29)
    np.testing.assert_allclose(bounds[known], balls[known], rtol=1e-5, atol=1e-6)
    if name.startswith("random"):
        return  # a warp at the top leaves most bounds unknown
    decided = (bounds[:, 1] < 0.5) | (bounds[:, 0] >= 0.5)
    assert 0.3 < decided.mean() < 1.0, "test set-up: the blocks should hold surface and empty space"


def test_block_bounds_bad_input():
    m = wb.Point((0, 0, 0), 1.0)
    for origin, h, blocks in [((0, 0), 0.1, [[0, 0, 0]]), ((0, 0, 0), -1.0, [[0, 0, 0]]), ((0, 0, 0), 0.1, [[0.5, 0, 0]])]:
        with pytest.raises(wb.WarpblobError, match="bound_blocks"):
            bound_blocks(m, origin, h, blocks)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_bounds_hold_for_sampled_points(name, device):
    model = MODELS[name]()
    rng = np.random.default_rng(5)
    lo, hi = model.bounds()
    centers = rng.uniform(lo, hi, (1500, 3))
    radii = rng.uniform(0.005, 0.4, 1500)
    bounds = bound_balls(model, centers, radii, device=device)
    pts = _ball_samples(rng, centers, radii, 8)
    f = reference_evaluate(model, pts.reshape(-1, 3))[0].reshape(len(centers), -1)
    assert np.all(f >= bounds[:, :1] - 2e-6), "a sampled point lies below its ball's F_min"
    assert np.all(f <= bounds[:, 1:] + 2e-6), "a sampled point lies above its ball's F_max"
    # the bounds are useful, not just [0, inf): many balls are decided
    decided = (bounds[:, 1] < 0.5) | (bounds[:, 0] >= 0.5)
    assert decided.mean() > 0.3


def test_warps_and_sketches_are_unknown_not_wrong(device):
    twisted = wb.Twist(wb.Box((0, 0, 0), (1, 0.2, 0.2), 0.2), (1, 0, 0), 2.0)
    inflated = wb.Inflate(wb.Sketch([[0, 0], [1, 0], [1, 1], [0, 1]]), thickness=0.2, radius=0.3)
    for model in (twisted, inflated):
        b = bound_balls(model, np.zeros((1, 3)), np.array([0.05]), device=device)
        f = wb.field(model, np.zeros((1, 3)), device=device)
        assert b[0, 0] <= f[0] <= b[0, 1]
        far = bound_balls(model, np.array([[50.0, 50.0, 50.0]]), np.array([0.1]), device=device)
        assert far.tolist() == [[0.0, 0.0]]


def test_radii_length_mismatch_raises():
    with pytest.raises(wb.WarpblobError, match="expected 2 values, got 3"):
        bound_balls(wb.scenes.peanut(), np.zeros((2, 3)), np.ones(3))
