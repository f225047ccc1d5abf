"""Tetrahedral mesh quality: the measures the thesis reports for every mesh (SPEC section 3).

Per tet, one Warp thread computes the signed volume, the six dihedral angles,
the aspect ratio ``beta = CR / (3 IR)`` (CR the circumsphere radius,
``IR = 3 V / sum of face areas`` the insphere radius; 1 for a regular tet,
growing without bound as the tet flattens) and its shortest and longest edge.
The mesh summary follows the thesis (Shirazian 2014): minimum and maximum
dihedral angle, Vmax/Vmin, lmax/lmin and the range of the aspect ratio.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from .._device import resolve_device
from .._parallel import launch
from ._tetmesh import TET_EDGES_WP, TET_FACES_WP

if TYPE_CHECKING:
    from ._tetmesh import TetMesh

__all__ = ["TetQuality", "quality", "format_quality"]

#: dihedral angle histogram bins, degrees
DIHEDRAL_BINS = np.linspace(0.0, 180.0, 19)
#: aspect ratio (beta) histogram bins; the first bin catches rounding just below 1
ASPECT_RATIO_BINS = np.array([0.0, 1.5, 2.0, 3.0, 5.0, 10.0, 100.0, 1e3, 1e6, np.inf])

_mat43d = wp.types.matrix(shape=(4, 3), dtype=wp.float64)


@wp.kernel(enable_backward=False)
def measure_tets_kernel(
    nodes: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    offset: int,
    volume: wp.array(dtype=wp.float64),
    dihedral: wp.array2d(dtype=wp.float64),
    dihedral_min: wp.array(dtype=wp.float64),
    dihedral_max: wp.array(dtype=wp.float64),
    aspect_ratio: wp.array(dtype=wp.float64),
    edge_min: wp.array(dtype=wp.float64),
    edge_max: wp.array(dtype=wp.float64),
):
    """Quality of tet ``t`` (float64 throughout: nearly flat tets are the ones that matter)."""
    t = wp.tid() + offset
    tet = tets[t]
    p0 = wp.vec3d(nodes[tet[0]])
    a = wp.vec3d(nodes[tet[1]]) - p0
    b = wp.vec3d(nodes[tet[2]]) - p0
    c = wp.vec3d(nodes[tet[3]]) - p0
    det = wp.dot(a, wp.cross(b, c))
    volume[t] = det / wp.float64(6.0)

    # outward area vectors of the four faces (inward, all four, for an inverted tet)
    area = wp.float64(0.0)
    normals = _mat43d()
    for k in range(4):
        q0 = wp.vec3d(nodes[tet[TET_FACES_WP[k, 0]]])
        q1 = wp.vec3d(nodes[tet[TET_FACES_WP[k, 1]]])
        q2 = wp.vec3d(nodes[tet[TET_FACES_WP[k, 2]]])
        n = wp.float64(0.5) * wp.cross(q1 - q0, q2 - q0)
        normals[k] = n
        area += wp.length(n)

    # the dihedral angle at edge j lies between the faces opposite the ends of edge 5 - j
    lo = wp.float64(180.0)
    hi = wp.float64(0.0)
    shortest = wp.float64(wp.inf)
    longest = wp.float64(0.0)
    for j in range(6):
        nu = normals[TET_EDGES_WP[5 - j, 0]]
        nv = normals[TET_EDGES_WP[5 - j, 1]]
        lu = wp.length(nu)
        lv = wp.length(nv)
        angle = wp.float64(0.0)
        if lu > wp.float64(0.0) and lv > wp.float64(0.0):
            cosine = wp.clamp(-wp.dot(nu, nv) / (lu * lv), wp.float64(-1.0), wp.float64(1.0))
            angle = wp.acos(cosine) * wp.float64(57.29577951308232)
        dihedral[t, j] = angle
        lo = wp.min(lo, angle)
        hi = wp.max(hi, angle)
        length = wp.length(
            wp.vec3d(nodes[tet[TET_EDGES_WP[j, 1]]]) - wp.vec3d(nodes[tet[TET_EDGES_WP[j, 0]]])
        )
        shortest = wp.min(shortest, length)
        longest = wp.max(longest, length)
    dihedral_min[t] = lo
    dihedral_max[t] = hi
    edge_min[t] = shortest
    edge_max[t] = longest

    # circumcentre offset from p0: (|a|^2 b x c + |b|^2 c x a + |c|^2 a x b) / (2 det)
    beta = wp.float64(wp.inf)
    if det != wp.float64(0.0):
        num = wp.dot(a, a) * wp.cross(b, c) + wp.dot(b, b) * wp.cross(c, a) + wp.dot(c, c) * wp.cross(a, b)
        circumradius = wp.length(num) / (wp.float64(2.0) * wp.abs(det))
        inradius = wp.float64(3.0) * wp.abs(det) / wp.float64(6.0) / area
        beta = circumradius / (wp.float64(3.0) * inradius)
    aspect_ratio[t] = beta


@dataclass(eq=False, repr=False)
class TetQuality:
    """Per-tet quality arrays and the mesh summary (SPEC section 3).

    Attributes:
        node_count: nodes of the mesh.
        tet_volume: (T,) float64 signed volume, model units cubed (negative: inverted).
        tet_dihedral: (T, 6) float64 dihedral angle at each edge (``TET_EDGES`` order), degrees.
        tet_dihedral_min: (T,) float64 smallest dihedral angle of the tet, degrees.
        tet_dihedral_max: (T,) float64 largest dihedral angle of the tet, degrees.
        tet_aspect_ratio: (T,) float64 ``beta = CR / (3 IR)``: 1 for a regular tet,
            larger for worse ones, ``inf`` for a flat one.
        tet_edge_min: (T,) float64 shortest edge of the tet, model units.
        tet_edge_max: (T,) float64 longest edge of the tet, model units.
        dihedral_histogram: (counts, bin edges in degrees) of all 6 T dihedral angles.
        aspect_ratio_histogram: (counts, bin edges) of ``tet_aspect_ratio``.

    The summary properties are NaN for a mesh without tets.
    """

    node_count: int
    tet_volume: np.ndarray
    tet_dihedral: np.ndarray
    tet_dihedral_min: np.ndarray
    tet_dihedral_max: np.ndarray
    tet_aspect_ratio: np.ndarray
    tet_edge_min: np.ndarray
    tet_edge_max: np.ndarray
    dihedral_histogram: tuple[np.ndarray, np.ndarray]
    aspect_ratio_histogram: tuple[np.ndarray, np.ndarray]

    @property
    def tet_count(self) -> int:
        return int(self.tet_volume.shape[0])

    @property
    def tet_edge_ratio(self) -> np.ndarray:
        """(T,) longest over shortest edge of each tet."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.tet_edge_max / self.tet_edge_min

    def _reduce(self, fn, values) -> float:
        return float(fn(values)) if values.size else float("nan")

    @property
    def volume(self) -> float:
        """Total signed volume, model units cubed."""
        return float(self.tet_volume.sum())

    @property
    def dihedral_min(self) -> float:
        """Smallest dihedral angle of the mesh, degrees."""
        return self._reduce(np.min, self.tet_dihedral_min)

    @property
    def dihedral_max(self) -> float:
        """Largest dihedral angle of the mesh, degrees."""
        return self._reduce(np.max, self.tet_dihedral_max)

    @property
    def volume_ratio(self) -> float:
        """Vmax/Vmin of the absolute tet volumes (``inf`` with a flat tet)."""
        v = np.abs(self.tet_volume)
        if not v.size:
            return float("nan")
        return float(v.max() / v.min()) if v.min() > 0 else float("inf")

    @property
    def edge_ratio(self) -> float:
        """lmax/lmin: the mesh's longest edge over its shortest."""
        if not self.tet_count:
            return float("nan")
        lo = self.tet_edge_min.min()
        return float(self.tet_edge_max.max() / lo) if lo > 0 else float("inf")

    @property
    def aspect_ratio_min(self) -> float:
        """Smallest beta of the mesh (its best tet; 1 is a regular tet)."""
        return self._reduce(np.min, self.tet_aspect_ratio)

    @property
    def aspect_ratio_max(self) -> float:
        """Largest beta of the mesh (its worst tet)."""
        return self._reduce(np.max, self.tet_aspect_ratio)

    @property
    def inverted_count(self) -> int:
        """Tets with volume <= 0."""
        return int(np.count_nonzero(self.tet_volume <= 0))

    def __repr__(self) -> str:
        return (
            f"TetQuality: {self.tet_count:,} tets, {self.node_count:,} nodes, volume {self.volume:.6g}\n"
            f"  dihedral angles [{self.dihedral_min:.2f}, {self.dihedral_max:.2f}] deg, "
            f"inverted tets {self.inverted_count:,}\n"
            f"  aspect ratio (beta) [{self.aspect_ratio_min:.4g}, {self.aspect_ratio_max:.4g}], "
            f"Vmax/Vmin {self.volume_ratio:.4g}, lmax/lmin {self.edge_ratio:.4g}"
        )

    def summary(self) -> dict:
        """The mesh summary as a dict of plain numbers (for stats, JSON and the CLI)."""
        return {
            "node_count": self.node_count,
            "tet_count": self.tet_count,
            "volume": self.volume,
            "dihedral_min": self.dihedral_min,
            "dihedral_max": self.dihedral_max,
            "volume_ratio": self.volume_ratio,
            "edge_ratio": self.edge_ratio,
            "aspect_ratio_min": self.aspect_ratio_min,
            "aspect_ratio_max": self.aspect_ratio_max,
            "inverted_count": self.inverted_count,
        }


def quality(tetmesh: TetMesh, *, device=None, threads: int | None = None) -> TetQuality:
    """Measure every tet of ``tetmesh`` (one Warp thread per tet).

    Args:
        tetmesh: the mesh.
        device: Warp device (default: Warp's default device).
        threads: CPU threads (default: :func:`warpblob.thread_count`).

    Returns:
        A :class:`TetQuality`.

    Example:
        >>> import numpy as np
        >>> from warpblob.mesh import TetMesh, quality
        >>> s = np.sqrt(2.0) / 2  # a regular tet: alternate corners of a cube
        >>> q = quality(TetMesh(s * np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]]), [[0, 1, 2, 3]]))
        >>> round(q.dihedral_min, 4), round(q.aspect_ratio_min, 6), q.inverted_count
        (70.5288, 1.0, 0)
    """

    dev = resolve_device(device)
    n = tetmesh.tet_count
    nodes = wp.array(tetmesh.nodes, dtype=wp.vec3, device=dev)
    tets = wp.array(tetmesh.tets, dtype=wp.vec4i, device=dev)
    volume = wp.empty(n, dtype=wp.float64, device=dev)
    dihedral = wp.empty((n, 6), dtype=wp.float64, device=dev)
    lo, hi, beta, emin, emax = (wp.empty(n, dtype=wp.float64, device=dev) for _ in range(5))
    launch(measure_tets_kernel, n, [nodes, tets], [volume, dihedral, lo, hi, beta, emin, emax], dev, threads)
    angles = dihedral.numpy()
    betas = beta.numpy()
    return TetQuality(
        node_count=tetmesh.node_count,
        tet_volume=volume.numpy(),
        tet_dihedral=angles,
        tet_dihedral_min=lo.numpy(),
        tet_dihedral_max=hi.numpy(),
        tet_aspect_ratio=betas,
        tet_edge_min=emin.numpy(),
        tet_edge_max=emax.numpy(),
        dihedral_histogram=np.histogram(angles, bins=DIHEDRAL_BINS),
        aspect_ratio_histogram=np.histogram(betas, bins=ASPECT_RATIO_BINS),
    )


def _bars(counts: np.ndarray, labels: list[str], width: int = 40) -> list[str]:
    top = max(int(counts.max()), 1) if counts.size else 1
    pad = max(len(s) for s in labels)
    return [f"  {s:>{pad}} {int(c):>10,} {'#' * int(round(width * c / top))}".rstrip() for s, c in zip(labels, counts)]


def format_quality(q: TetQuality) -> str:
    """A plain-text quality report (counts, the SPEC section 3 summary and both histograms).

    Example:
        >>> import numpy as np
        >>> from warpblob.mesh import TetMesh, format_quality
        >>> print(format_quality(TetMesh(np.eye(4, 3, k=-1), [[0, 1, 2, 3]]).quality()).splitlines()[0])
        tets 1  nodes 4  volume 0.166667
    """
    s = q.summary()
    lines = [
        f"tets {s['tet_count']:,}  nodes {s['node_count']:,}  volume {s['volume']:.6g}",
        f"dihedral angle        min {s['dihedral_min']:.2f} deg  max {s['dihedral_max']:.2f} deg",
        f"Vmax/Vmin             {s['volume_ratio']:.4g}",
        f"lmax/lmin             {s['edge_ratio']:.4g}",
        f"aspect ratio (beta)   min {s['aspect_ratio_min']:.4g}  max {s['aspect_ratio_max']:.4g}  (1 = regular tet)",
        f"inverted tets         {s['inverted_count']:,}",
        "dihedral angles (deg):",
    ]
    counts, edges = q.dihedral_histogram
    lines += _bars(counts, [f"{edges[i]:.0f}-{edges[i + 1]:.0f}" for i in range(len(counts))])
    lines.append("aspect ratio (beta):")
    counts, edges = q.aspect_ratio_histogram
    labels = [f"< {edges[1]:g}"] + [f"{edges[i]:g}-{edges[i + 1]:g}" for i in range(1, len(counts))]
    labels[-1] = f">= {edges[-2]:g}"
    lines += _bars(counts, labels)
    return "\n".join(lines)
