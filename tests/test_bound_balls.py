"""Interval bounds of the field over balls: every sampled point lies within them."""

import numpy as np
import pytest

import warpblob as wb
from reference import reference_evaluate
from warpblob.field import bound_balls


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
