"""Volume of a model by Monte Carlo integration of its inside set.

An estimate independent of any mesh, so a polygonization or tetrahedralization
can be checked against the model itself: points uniform in the model's box,
inside where ``F >= iso``; the volume is the box's volume times the fraction
inside, with the binomial standard error (e.g. Press et al., *Numerical
Recipes*, section 7.7, simple Monte Carlo integration).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from .._errors import ModelError
from .._linearize import linearize
from ..tree import ISO_VALUE
from ._engine import field

__all__ = ["VolumeEstimate", "monte_carlo_volume"]


@dataclass(frozen=True)
class VolumeEstimate:
    """A Monte Carlo volume: ``volume`` +- ``standard_error`` (model units cubed)."""

    volume: float
    standard_error: float
    samples: int
    inside_fraction: float
    #: wall-clock seconds of the field evaluation (warm)
    seconds: float

    def as_dict(self) -> dict:
        """The fields as a plain dict (for JSON summaries)."""
        return asdict(self)


def monte_carlo_volume(
    model, *, samples: int = 1_000_000, rng: np.random.Generator | int | None = 0, iso: float = ISO_VALUE, device=None
) -> VolumeEstimate:
    """Monte Carlo estimate of the volume enclosed by ``model``'s iso-surface.

    ``samples`` points uniform in the model's box ``B``; with ``p`` the fraction
    inside (``F >= iso``) the volume is ``|B| p`` and its standard error
    ``|B| sqrt(p (1 - p) / samples)``.

    Args:
        model: a model (:class:`~warpblob.tree.Node`) or its :class:`~warpblob.LinearModel`.
        samples: number of points (at least 1).
        rng: a numpy Generator or a seed for one.
        iso: the iso-value bounding the solid.
        device: Warp device of the field evaluation.

    Returns:
        A :class:`VolumeEstimate`.

    Raises:
        ModelError: ``samples`` below 1.

    Example:
        >>> import numpy as np, warpblob as wb
        >>> ball = wb.Point((0, 0, 0), 1.0)  # a sphere of radius ISO_DISTANCE
        >>> mc = wb.monte_carlo_volume(ball, samples=100_000)
        >>> bool(abs(mc.volume - 4 / 3 * np.pi * wb.ISO_DISTANCE**3) < 4 * mc.standard_error)
        True
    """
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ModelError(f"monte_carlo_volume: samples must be a positive integer, got {samples!r}")
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    lm = linearize(model)
    lo, hi = (np.asarray(b, dtype=np.float64) for b in lm.bounds)
    if np.any(lo > hi):
        return VolumeEstimate(0.0, 0.0, int(samples), 0.0, 0.0)
    box = float(np.prod(hi - lo))
    points = rng.uniform(lo, hi, (int(samples), 3)).astype(np.float32)
    field(lm, points[:1000], device=device)  # compile and warm up outside the timing
    t0 = time.perf_counter()
    inside = field(lm, points, device=device) >= iso
    seconds = time.perf_counter() - t0
    p = float(np.mean(inside))
    return VolumeEstimate(box * p, box * float(np.sqrt(p * (1.0 - p) / samples)), int(samples), p, seconds)
