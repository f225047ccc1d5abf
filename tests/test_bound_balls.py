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


def _sub_block_cubes(origin, h, blocks):
    """Centres (N, 64, 3) and half side of the sub-block cubes of ``bound_blocks``,
    in float32 as the kernel computes them."""
    s = np.arange(4)
    sk, sj, si = np.meshgrid(s, s, s, indexing="ij")
    local = np.stack([si, sj, sk], axis=-1).reshape(64, 3)
    index = (8 * blocks[:, None, :] + 2 * local[None] + 1).astype(np.float32)
    h = np.float32(h)
    return origin.astype(np.float32) + h * index, h


def _cube_samples(rng, centers, half, per_cube):
    """Points of each cube: its 8 corners, its centre and ``per_cube`` uniform ones."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)] + [[0, 0, 0]], dtype=np.float64)
    d = np.concatenate([np.broadcast_to(corners, (len(centers), 9, 3)), rng.uniform(-1, 1, (len(centers), per_cube, 3))], axis=1)
    return centers[:, None, :] + half * d


@pytest.mark.parametrize("name", sorted(MODELS) + ["random-0", "random-3"])
def test_block_bounds_hold_and_are_tighter_than_ball_bounds(name, device):
    """One tree walk per block (bounds rows) bounds its 64 sub-block cubes:
    every sampled point of a cube (corners, centre, random) lies within them,
    and they are never looser than the per-ball bounds at the cubes'
    circumscribed balls (the tangent-plane bound of convex skeletons only
    tightens them)."""
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
    centers, half = _sub_block_cubes(origin, h, blocks)
    centers, bounds = centers.reshape(-1, 3), bounds.reshape(-1, 2)
    pts = _cube_samples(rng, centers.astype(np.float64), float(half), 6)
    f = reference_evaluate(model, pts.reshape(-1, 3))[0].reshape(len(centers), -1)
    assert np.all(f >= bounds[:, :1] - 2e-6), "a sampled point lies below its sub-block's F_min"
    assert np.all(f <= bounds[:, 1:] + 2e-6), "a sampled point lies above its sub-block's F_max"
    radius = half * np.float32(1.7320509) * np.float32(1.0001)
    balls = bound_balls(model, centers, np.full(len(centers), radius), device=device)
    assert np.all(bounds[:, 0] >= balls[:, 0] * (1 - 1e-5) - 1e-6), "a cube's F_min is below its ball's"
    assert np.all(bounds[:, 1] <= balls[:, 1] * (1 + 1e-5) + 1e-6), "a cube's F_max is above its ball's"
    if name.startswith("random"):
        return  # a warp at the top leaves most bounds unknown
    decided = (bounds[:, 1] < 0.5) | (bounds[:, 0] >= 0.5)
    assert 0.3 < decided.mean() < 1.0, "test set-up: the blocks should hold surface and empty space"


def test_cube_bounds_decide_more_than_ball_bounds(device):
    """Near a flat face parallel to the grid (a box skeleton) the tangent-plane
    bound decides sub-blocks the ball bound cannot: a cube whose nearest point
    is a distance D from the face is decided once D clears the iso-distance,
    a ball only once its centre is sqrt(3) half sides further out."""
    model = wb.Box((0.0, 0.0, 0.0), (2.0, 2.0, 0.0), 0.5)  # a square plate, iso at 0.227 from it
    h = 0.05
    origin = np.array([-1.0, -1.0, -0.77], dtype=np.float32)  # cube centres at |z| = 0.28: 0.053 past the iso-surface
    blocks = np.array([[i, j, k] for i in range(5) for j in range(5) for k in range(4)])
    bounds = bound_blocks(model, origin, h, blocks, device=device).reshape(-1, 2)
    centers, half = _sub_block_cubes(origin, h, blocks)
    centers = centers.reshape(-1, 3).astype(np.float64)
    balls = bound_balls(model, centers, np.full(len(centers), half * 1.7320509 * 1.0001), device=device)
    decided = (bounds[:, 1] < 0.5) | (bounds[:, 0] >= 0.5)
    ball_decided = (balls[:, 1] < 0.5) | (balls[:, 0] >= 0.5)
    assert np.all(decided | ~ball_decided)
    # outside the plate's middle the only undecided cubes are those within a
    # cell of the iso-surface (inside, F_min still comes from the ball)
    middle = np.all(np.abs(centers[:, :2]) < 0.5, axis=1)
    gap = np.abs(centers[:, 2]) - 0.5 * (1 - 0.5 ** (1 / 3)) ** 0.5  # |z| minus the iso-distance
    clear = middle & (gap > 1.01 * h)
    assert clear.sum() > 100
    assert np.all(decided[clear])
    band = clear & (gap < 1.7 * h)  # past the iso-surface by more than h, less than the ball's sqrt(3) h
    assert band.sum() > 50
    assert not np.any(ball_decided[band])


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
