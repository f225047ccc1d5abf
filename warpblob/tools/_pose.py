"""Rigid poses: a position and a unit quaternion, single or batched.

Quaternions are stored (x, y, z, w), the order of ``wp.quat`` and of the
rotation part of ``wp.transform``, so ``Pose.numpy()`` loads straight into a
``wp.array(dtype=wp.transform)``. A pose maps a local point ``p`` to the
world point ``R(q) p + position`` (rotate about the local origin, then
translate); ``matrix()`` is that map as a 4x4 for column vectors.

Interpolation is Shoemake's spherical linear interpolation (K. Shoemake,
"Animating rotation with quaternion curves", SIGGRAPH 1985) along the
shorter arc; rotation matrices are turned into quaternions by Shepperd's
method (S. W. Shepperd, "Quaternion from rotation matrix", Journal of
Guidance and Control 1(3), 1978), which divides by the largest of the four
components so that no rotation loses precision.
"""

from __future__ import annotations

import numpy as np

from .._errors import ToolError
from ._check import frozen, rows, shown, unit_quaternions

__all__ = ["Pose"]

# world up (the stage's upAxis is Z) and the reference used instead when the travel is vertical
_UP = np.array([0.0, 0.0, 1.0])
_UP_FALLBACK = np.array([0.0, 1.0, 0.0])
# sine of the angle from vertical under which a travel direction counts as vertical
_VERTICAL = 1e-6
# largest entry of R^T R - I (and of the last row's deviation) that still counts as a rigid motion
_RIGID_TOLERANCE = 1e-5


def quaternion_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions (..., 4) given as (x, y, z, w)."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def matrix_quaternions(m: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4), (x, y, z, w) with w >= 0, of rotation matrices (..., 3, 3) (Shepperd 1978)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    # 4 w^2, 4 x^2, 4 y^2, 4 z^2; the largest is the safe one to divide by
    sq = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1)
    k = np.argmax(sq, axis=-1)
    big = 0.5 * np.sqrt(np.maximum(np.take_along_axis(sq, k[..., None], axis=-1)[..., 0], 1e-300))
    d = 0.25 / big
    a = (m[..., 2, 1] - m[..., 1, 2]) * d  # 4 w x
    b = (m[..., 0, 2] - m[..., 2, 0]) * d  # 4 w y
    c = (m[..., 1, 0] - m[..., 0, 1]) * d  # 4 w z
    e = (m[..., 0, 1] + m[..., 1, 0]) * d  # 4 x y
    f = (m[..., 0, 2] + m[..., 2, 0]) * d  # 4 x z
    g = (m[..., 1, 2] + m[..., 2, 1]) * d  # 4 y z
    candidates = np.stack(
        [
            np.stack([a, b, c, big], axis=-1),
            np.stack([big, e, f, a], axis=-1),
            np.stack([e, big, g, b], axis=-1),
            np.stack([f, g, big, c], axis=-1),
        ],
        axis=-2,
    )
    q = np.take_along_axis(candidates, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    # one sign per rotation, and + 0.0 turns -0.0 into 0.0, so equal rotations give equal arrays
    return np.where(q[..., 3:] < 0, -q, q) + 0.0


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation (Shoemake 1985) of unit quaternions (..., 4) at ``u`` (...) in [0, 1].

    Takes the shorter arc (``q1`` and ``-q1`` are the same rotation). Where
    the two are within about 1e-6 rad the weights of plain linear
    interpolation are used, since ``sin(theta)`` would divide by nearly zero.
    """
    u = np.asarray(u, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    theta = np.arccos(np.clip(np.abs(dot), 0.0, 1.0))
    s = np.sin(theta)
    near = s < 1e-6
    s = np.where(near, 1.0, s)
    w0 = np.where(near, 1.0 - u, np.sin((1.0 - u) * theta) / s)
    w1 = np.where(near, u, np.sin(u * theta) / s)
    q = w0 * q0 + w1 * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def along_matrices(d: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) taking local -z to unit directions ``d`` (..., 3), local +y as near world +z as it goes.

    This is the look-at frame of a USD or OpenGL camera (which looks down its
    -z with +y up) with the stage's Z up. For travel within 1e-6 rad of
    vertical, where "as near up as possible" has no answer, local +y goes to
    the world +y instead: straight down is then the identity.
    """
    y = _UP - (d @ _UP)[..., None] * d
    vertical = np.linalg.norm(y, axis=-1, keepdims=True) < _VERTICAL
    y = np.where(vertical, _UP_FALLBACK - (d @ _UP_FALLBACK)[..., None] * d, y)
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    z = -d
    return np.stack([np.cross(y, z), y, z], axis=-1)


class Pose:
    """A rigid pose (position and rotation), or a batch of N of them.

    A local point ``p`` goes to the world point ``R(q) p + position``. The
    rotation is a unit quaternion in the order (x, y, z, w) (Warp's
    ``wp.quat`` order; USD's ``Gf.Quatd`` takes the real part first).

    Args:
        position: (3,) or (N, 3) world position of the local origin, model units.
        rotation: (4,) or (N, 4) quaternion (x, y, z, w); scaled to unit
            length. Default: the identity. A single position or rotation is
            shared by every pose of a batch.

    Attributes:
        position: (3,) or (N, 3) float64, read-only.
        rotation: (4,) or (N, 4) float64 unit quaternions, read-only.

    Raises:
        ToolError: a shape is wrong, a value is not finite, a quaternion is
            zero, or the batch sizes of position and rotation differ.

    Example:
        >>> import numpy as np
        >>> from warpblob.tools import Pose
        >>> quarter = (0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4))  # 90 degrees about z
        >>> Pose((1, 2, 3), quarter).apply([1, 0, 0]).round(6)
        array([1., 3., 3.])
    """

    __slots__ = ("position", "rotation")

    def __init__(self, position=(0.0, 0.0, 0.0), rotation=None):
        p = rows("Pose", "position", position, 3, single=True)
        q = (
            np.array([0.0, 0.0, 0.0, 1.0])
            if rotation is None
            else unit_quaternions("Pose", "rotation", rotation, single=True)
        )
        if p.ndim == 2 and q.ndim == 2 and len(p) != len(q):
            raise ToolError(f"Pose: {len(p)} positions but {len(q)} rotations")
        if p.ndim != q.ndim:
            count = len(p) if p.ndim == 2 else len(q)
            p = np.broadcast_to(p, (count, 3)).copy()
            q = np.broadcast_to(q, (count, 4)).copy()
        self.position = frozen(p)
        self.rotation = frozen(q)

    @classmethod
    def _trusted(cls, position: np.ndarray, rotation: np.ndarray) -> Pose:
        """A pose from arrays already checked and normalized (the hot paths of Path skip validation)."""
        pose = object.__new__(cls)
        pose.position = frozen(np.ascontiguousarray(position, dtype=np.float64))
        pose.rotation = frozen(np.ascontiguousarray(rotation, dtype=np.float64))
        return pose

    @classmethod
    def from_matrix(cls, matrix) -> Pose:
        """The pose of a rigid 4x4 matrix for column vectors (``world = M @ [p, 1]``).

        Args:
            matrix: (4, 4) or (N, 4, 4). A USD matrix (row vectors) must be
                transposed first.

        Raises:
            ToolError: a shape is wrong, an entry is not finite, or a matrix
                scales, shears, mirrors or projects (beyond 1e-5).

        Example:
            >>> import numpy as np
            >>> from warpblob.tools import Pose
            >>> m = np.eye(4); m[:3, 3] = (1, 2, 3)
            >>> Pose.from_matrix(m).position
            array([1., 2., 3.])
        """
        try:
            m = np.array(matrix, dtype=np.float64)
        except (TypeError, ValueError):
            raise ToolError(
                f"Pose.from_matrix: matrix must be numbers of shape (4, 4) or (N, 4, 4), got {shown(matrix)}"
            ) from None
        if m.shape != (4, 4) and (m.ndim != 3 or m.shape[1:] != (4, 4)):
            raise ToolError(f"Pose.from_matrix: matrix must have shape (4, 4) or (N, 4, 4), got shape {m.shape}")
        single = m.ndim == 2
        pose = rigid_poses("Pose.from_matrix", m.reshape(-1, 4, 4), lambda i: "matrix" if single else f"matrix[{i}]")
        return pose[0] if single else pose

    @classmethod
    def along(cls, direction, position=(0.0, 0.0, 0.0)) -> Pose:
        """The pose whose local -z points along ``direction``: a tool that leads with its working end.

        The roll about the direction is fixed as for a camera: local +y is
        as near world +z (up) as possible, so a scalpel (cutting edge along
        local +y) travelling horizontally holds its edge vertical. For a
        direction within 1e-6 rad of vertical local +y goes to world +y;
        straight down is the identity, straight up a half turn about y.

        Args:
            direction: (3,) or (N, 3) direction of travel, any non-zero length.
            position: (3,) or (N, 3) world position of the local origin.

        Raises:
            ToolError: a direction is zero or not finite, or the shapes are wrong.

        Example:
            >>> from warpblob.tools import Pose
            >>> Pose.along((1, 0, 0)).rotate([0, 0, -1]).round(6) + 0.0
            array([1., 0., 0.])
        """
        d = rows("Pose.along", "direction", direction, 3, single=True)
        length = np.linalg.norm(d, axis=-1, keepdims=True)
        if np.any(length < 1e-12):
            raise ToolError(f"Pose.along: direction must be non-zero, got {shown(d)}")
        p = rows("Pose.along", "position", position, 3, single=True)
        return cls(p, matrix_quaternions(along_matrices(d / length)))

    @property
    def shape(self) -> tuple:
        """``()`` for a single pose, ``(N,)`` for a batch."""
        return self.position.shape[:-1]

    def __len__(self) -> int:
        if not self.shape:
            raise TypeError("len() of a single Pose")
        return self.shape[0]

    def __getitem__(self, index) -> Pose:
        if not self.shape:
            raise TypeError("a single Pose cannot be indexed")
        return Pose._trusted(self.position[index], self.rotation[index])

    def rotation_matrix(self) -> np.ndarray:
        """(3, 3) or (N, 3, 3) rotation matrices (column vectors)."""
        return quaternion_matrices(self.rotation)

    def matrix(self) -> np.ndarray:
        """(4, 4) or (N, 4, 4) homogeneous matrices for column vectors: ``world = M @ [p, 1]``."""
        m = np.zeros(self.shape + (4, 4))
        m[..., :3, :3] = self.rotation_matrix()
        m[..., :3, 3] = self.position
        m[..., 3, 3] = 1.0
        return m

    def rotate(self, vectors) -> np.ndarray:
        """Rotate local ``vectors`` (..., 3) into the world (no translation): directions, normals.

        Returns:
            ``self.shape + vectors.shape`` float64: every pose applied to every vector.
        """
        v = np.asarray(vectors, dtype=np.float64)
        r = self.rotation_matrix()
        flat = v.reshape(-1, 3)
        out = np.einsum("...ij,nj->...ni", r, flat)
        return out.reshape(self.shape + v.shape)

    def apply(self, points) -> np.ndarray:
        """Map local ``points`` (..., 3) to world points, model units.

        Returns:
            ``self.shape + points.shape`` float64: for a batch of N poses,
            every pose applied to every point, e.g. (N, M, 3) for (M, 3) points.
        """
        v = np.asarray(points, dtype=np.float64)
        extra = (1,) * (v.ndim - 1)
        return self.rotate(v) + self.position.reshape(self.shape + extra + (3,))

    def inverse(self) -> Pose:
        """The pose mapping world points back to local ones."""
        q = self.rotation * np.array([-1.0, -1.0, -1.0, 1.0])
        back = Pose._trusted(np.zeros_like(self.position), q)
        p = np.einsum("...ij,...j->...i", back.rotation_matrix(), self.position)
        return Pose._trusted(-p, q)

    def numpy(self) -> np.ndarray:
        """(7,) or (N, 7) float64 ``[px, py, pz, qx, qy, qz, qw]``: the memory layout of ``wp.transform``."""
        return np.concatenate([self.position, self.rotation], axis=-1)

    def __repr__(self) -> str:
        if self.shape:
            return f"Pose: batch of {self.shape[0]}"
        p = ", ".join(f"{v:.6g}" for v in self.position)
        q = ", ".join(f"{v:.6g}" for v in self.rotation)
        return f"Pose(position=({p}), rotation=({q}))"


def rigid_poses(owner: str, m: np.ndarray, name) -> Pose:
    """The (N,) batch of poses of (N, 4, 4) column-vector matrices, each checked to be a rigid motion.

    Rounding in a file (float angles, a printed matrix) leaves a rotation
    block slightly off orthonormal; its nearest rotation (the polar factor,
    by SVD) is used, so the quaternion is exact for what was meant.

    Args:
        owner: the caller, for messages.
        m: (N, 4, 4) float64.
        name: ``name(i)`` says which matrix ``i`` is (an index, a time code).

    Raises:
        ToolError: a matrix is not finite, or scales, shears, mirrors or
            projects by more than 1e-5.
    """
    finite = np.isfinite(m).reshape(len(m), 16).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise ToolError(f"{owner}: {name(i)} must be finite, got {shown(m[i])}")
    r = m[:, :3, :3]
    gram = np.abs(np.einsum("nki,nkj->nij", r, r) - np.eye(3)).reshape(len(m), 9).max(axis=1)
    row = np.abs(m[:, 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    bad = (np.maximum(gram, row) > _RIGID_TOLERANCE) | (np.linalg.det(r) <= 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise ToolError(
            f"{owner}: {name(i)} is not a rigid motion (it scales, shears, mirrors or projects): {shown(m[i])}"
        )
    u, _, vt = np.linalg.svd(r)
    return Pose._trusted(m[:, :3, 3], matrix_quaternions(u @ vt))
