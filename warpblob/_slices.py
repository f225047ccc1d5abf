"""Pictures of a model's field: axis-aligned slices through its box."""

from __future__ import annotations

import os

import numpy as np

from ._linearize import linearize
from .field import evaluate, field
from .tree import ISO_VALUE

__all__ = ["slice_planes", "save_slices"]

_AXES = (("x", "y", 2), ("x", "z", 1), ("y", "z", 0))


def _plane_points(lo, hi, fixed, offset, resolution):
    u_axis, v_axis = [a for a in range(3) if a != fixed]
    us = np.linspace(lo[u_axis], hi[u_axis], resolution)
    vs = np.linspace(lo[v_axis], hi[v_axis], resolution)
    uu, vv = np.meshgrid(us, vs)
    pts = np.empty((resolution * resolution, 3), dtype=np.float32)
    pts[:, fixed] = offset
    pts[:, u_axis] = uu.ravel()
    pts[:, v_axis] = vv.ravel()
    return pts, (us[0], us[-1], vs[0], vs[-1])


def slice_planes(model, *, resolution: int = 256, device=None):
    """Field and colour on three axis-aligned planes through the model.

    Each plane sits at the offset (of 15 across the box) that cuts the most
    solid, so models with gaps at their centre (a grid of towers) still show.

    Returns:
        list of ``(title, extent, values (res, res), colors (res, res, 3))``
        with ``extent = (u0, u1, v0, v1)`` in model units.
    """
    lm = linearize(model)
    lo, hi = lm.bounds
    out = []
    for u_name, v_name, fixed in _AXES:
        offsets = np.linspace(lo[fixed], hi[fixed], 17)[1:-1]
        probes = np.concatenate([_plane_points(lo, hi, fixed, o, 48)[0] for o in offsets])
        inside = (field(lm, probes, device=device) >= ISO_VALUE).reshape(len(offsets), -1).sum(axis=1)
        offset = offsets[int(np.argmax(inside))] if inside.max() > 0 else 0.5 * (lo[fixed] + hi[fixed])
        pts, extent = _plane_points(lo, hi, fixed, offset, resolution)
        values, _, colors = evaluate(lm, pts, device=device)
        title = f"{u_name}{v_name} plane, {'xyz'[fixed]} = {offset:.2f}"
        out.append((title, extent, values.reshape(resolution, resolution), colors.reshape(resolution, resolution, 3)))
    return out


def save_slices(model, path: str, *, name: str = "", resolution: int = 256, device=None) -> str:
    """Write a PNG of the three centre slices of ``model`` to ``path`` (atomically).

    Inside (``F >= 0.5``) shows the model's colour, outside a grey ramp of the
    field; the iso-contour is drawn in black.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    planes = slice_planes(model, resolution=resolution, device=device)
    fig, axes = plt.subplots(1, 3, figsize=(13.5, 4.6), dpi=100)
    for ax, (title, extent, values, colors) in zip(axes, planes):
        shade = np.clip(values / ISO_VALUE, 0.0, 1.0)[..., None]
        grey = 1.0 - 0.55 * shade
        image = np.where((values >= ISO_VALUE)[..., None], colors, grey * np.ones(3))
        ax.imshow(image, origin="lower", extent=extent, interpolation="nearest")
        if values.max() > ISO_VALUE > values.min():
            ax.contour(values, levels=[ISO_VALUE], colors="k", linewidths=0.8, extent=extent, origin="lower")
        ax.set_title(title, fontsize=10)
        ax.set_aspect("equal")
    fig.suptitle(f"{name}: field slices (colour inside F >= 0.5, grey ramp outside)", fontsize=11)
    fig.tight_layout()
    tmp = path + ".tmp.png"
    fig.savefig(tmp)
    plt.close(fig)
    os.replace(tmp, path)
    return path
