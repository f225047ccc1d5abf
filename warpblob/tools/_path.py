"""Tool paths: poses keyed in time, read from and written to time-sampled USD transforms.

Between keys the position moves linearly and the rotation turns by
spherical linear interpolation along the shorter arc (K. Shoemake,
"Animating rotation with quaternion curves", SIGGRAPH 1985), so a tool
moves at constant speed and turns at constant angular speed over each
interval. Before the first key and after the last the tool rests at that
key's pose. Times are seconds; positions are model units.
"""

from __future__ import annotations

import os

import numpy as np

from .._errors import SceneError, ToolError
from ._check import frozen, rows, scalar, shown, unit_quaternions
from ._pose import Pose, rigid_poses, slerp

__all__ = ["Path"]

# a polyline aligned to its travel turns over this fraction of the shorter segment on each side of a corner
_CORNER_FRACTION = 0.25


class Path:
    """Poses of a rigid tool over time: keyed positions and rotations, interpolated between keys.

    ``pose(t)`` interpolates linearly in position and by slerp (Shoemake
    1985) in rotation, and clamps ``t`` to ``[t0, t1]``: before ``t0`` the
    tool rests at the first key, after ``t1`` at the last. Consecutive key
    rotations are interpolated along the shorter arc (the stored quaternions
    are sign-flipped so that neighbours have a non-negative dot product); to
    turn by more than half a turn between two times, add keys in between.

    Args:
        times: (N,) seconds, strictly increasing, N >= 1 (one key: a tool at rest).
        positions: (N, 3) world positions of the tool's local origin, model units.
        rotations: (N, 4) quaternions (x, y, z, w), scaled to unit length;
            default: the identity at every key.

    Attributes:
        times: (N,) float64 seconds, read-only.
        positions: (N, 3) float64, read-only.
        rotations: (N, 4) float64 unit quaternions, read-only.

    Raises:
        ToolError: times not strictly increasing, a NaN or infinite time,
            position or rotation, a zero quaternion, or wrong shapes; the
            message names the first bad key.

    Example:
        >>> import numpy as np
        >>> from warpblob.tools import Path
        >>> quarter = (0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4))  # 90 degrees about z
        >>> path = Path([0.0, 2.0], [(0, 0, 0), (2, 0, 0)], [(0, 0, 0, 1), quarter])
        >>> pose = path.pose(1.0)
        >>> pose.position, round(float(np.degrees(2 * np.arccos(pose.rotation[3]))), 6)
        (array([1., 0., 0.]), 45.0)
    """

    def __init__(self, times, positions, rotations=None):
        try:
            t = np.array(times, dtype=np.float64)
        except (TypeError, ValueError):
            raise ToolError(f"Path: times must be numbers of shape (N,), got {shown(times)}") from None
        if t.ndim != 1 or len(t) < 1:
            raise ToolError(f"Path: times must have shape (N,) with N >= 1, got shape {t.shape}")
        if not np.isfinite(t).all():
            i = int(np.argmin(np.isfinite(t)))
            raise ToolError(f"Path: times[{i}] must be finite, got {float(t[i])!r}")
        rising = np.diff(t) > 0
        if not rising.all():
            i = int(np.argmin(rising)) + 1
            raise ToolError(
                f"Path: times must be strictly increasing, got times[{i}] = {float(t[i])!r} after times[{i - 1}] = "
                f"{float(t[i - 1])!r}"
            )
        p = rows("Path", "positions", positions, 3)
        if len(p) != len(t):
            raise ToolError(f"Path: {len(t)} times but {len(p)} positions")
        if rotations is None:
            q = np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1))
        else:
            q = unit_quaternions("Path", "rotations", rotations)
            if len(q) != len(t):
                raise ToolError(f"Path: {len(t)} times but {len(q)} rotations")
            # flip each key into the hemisphere of the one before, so every interval is the shorter arc
            flip = np.concatenate([[1.0], np.where(np.sum(q[1:] * q[:-1], axis=1) < 0, -1.0, 1.0)])
            q = q * np.cumprod(flip)[:, None]
        self.times = frozen(t)
        self.positions = frozen(p)
        self.rotations = frozen(q)

    @classmethod
    def line(cls, start, end, duration, *, align: bool = False, t0: float = 0.0) -> Path:
        """A straight stroke from ``start`` to ``end`` at constant speed.

        Args:
            start, end: (3,) world positions of the tool's origin, model units.
            duration: seconds, > 0.
            align: rotate the tool so that its local -z points along the
                travel (see :meth:`Pose.along`): a drill bores bit first, a
                scalpel leads with its edge. Otherwise the identity rotation.
            t0: start time, seconds.

        Raises:
            ToolError: a bad point, ``duration <= 0``, or ``align`` with ``start == end``.

        Example:
            >>> from warpblob.tools import Path
            >>> path = Path.line((0, 0, 1), (0, 0, -1), 4.0, align=True)  # straight down: no rotation
            >>> path.velocity(1.0), path.pose(1.0).rotation
            (array([ 0. ,  0. , -0.5]), array([0., 0., 0., 1.]))
        """
        a = rows("Path.line", "start", start, 3, single=True, batch=False)
        b = rows("Path.line", "end", end, 3, single=True, batch=False)
        duration = scalar("Path.line", "duration", duration, positive=True)
        t0 = scalar("Path.line", "t0", t0)
        rotations = None
        if align:
            if np.array_equal(a, b):
                raise ToolError(f"Path.line: align=True needs a direction, but start = end = {shown(a)}")
            rotations = np.tile(Pose.along(b - a).rotation, (2, 1))
        return cls([t0, t0 + duration], [a, b], rotations)

    @classmethod
    def polyline(cls, points, speed, *, align: bool = False, t0: float = 0.0) -> Path:
        """A stroke through ``points`` at constant ``speed``.

        With ``align``, the tool's local -z points along each segment (see
        :meth:`Pose.along`) and the tool turns at each corner while it
        moves: the turn is one slerp from the incoming segment's rotation to
        the outgoing one's, starting a quarter of the shorter of the two
        segments before the corner and ending as far after it. The tool is
        exactly aligned over at least the middle half of every segment, and
        the speed along the polyline stays constant.

        Args:
            points: (N, 3) world positions, N >= 2, no two consecutive equal, model units.
            speed: model units per second, > 0.
            align: see above; otherwise the identity rotation throughout.
            t0: time at ``points[0]``, seconds.

        Raises:
            ToolError: bad points, fewer than two, two consecutive equal, or ``speed <= 0``.

        Example:
            >>> from warpblob.tools import Path
            >>> path = Path.polyline([(0, 0, 0), (3, 0, 0), (3, 4, 0)], 2.0)
            >>> path.t1, path.direction(2.0)
            (3.5, array([0., 1., 0.]))
        """
        p = rows("Path.polyline", "points", points, 3)
        if len(p) < 2:
            raise ToolError(f"Path.polyline: points must have at least 2 rows, got {len(p)}")
        speed = scalar("Path.polyline", "speed", speed, positive=True)
        t0 = scalar("Path.polyline", "t0", t0)
        step = np.diff(p, axis=0)
        length = np.linalg.norm(step, axis=1)
        if not (length > 0).all():
            i = int(np.argmin(length > 0))
            raise ToolError(f"Path.polyline: points[{i}] and points[{i + 1}] coincide: {shown(p[i])}")
        s = np.concatenate([[0.0], np.cumsum(length)])
        if not align:
            return cls(t0 + s / speed, p)
        d = step / length[:, None]
        q = Pose.along(d).rotation
        # around each interior corner: a key where the turn begins, one at the corner (half-way), one where it ends
        reach = _CORNER_FRACTION * np.minimum(length[:-1], length[1:])
        corner = p[1:-1]
        keys = np.stack([corner - reach[:, None] * d[:-1], corner, corner + reach[:, None] * d[1:]], axis=1)
        arc = np.stack([s[1:-1] - reach, s[1:-1], s[1:-1] + reach], axis=1)
        turn = np.stack([q[:-1], slerp(q[:-1], q[1:], 0.5), q[1:]], axis=1)
        return cls(
            t0 + np.concatenate([[0.0], arc.ravel(), s[-1:]]) / speed,
            np.concatenate([p[:1], keys.reshape(-1, 3), p[-1:]]),
            np.concatenate([q[:1], turn.reshape(-1, 4), q[-1:]]),
        )

    @property
    def key_count(self) -> int:
        return len(self.times)

    @property
    def t0(self) -> float:
        """Time of the first key, seconds."""
        return float(self.times[0])

    @property
    def t1(self) -> float:
        """Time of the last key, seconds."""
        return float(self.times[-1])

    @property
    def duration(self) -> float:
        """``t1 - t0``, seconds."""
        return self.t1 - self.t0

    def _interval(self, t, who: str):
        """``(t, i, j, u, scalar)``: each time's interval between keys ``i`` and ``j = i + 1`` and its fraction ``u``.

        Times are clamped to ``[t0, t1]``; ``t1`` itself falls in the last
        interval. A one-key path has ``i = j = 0``.
        """
        try:
            t = np.asarray(t, dtype=np.float64)
        except (TypeError, ValueError):
            raise ToolError(f"Path.{who}: t must be a number or an (N,) array of seconds, got {shown(t)}") from None
        if t.ndim > 1:
            raise ToolError(f"Path.{who}: t must be a number or an (N,) array of seconds, got shape {t.shape}")
        if not np.isfinite(t).all():
            raise ToolError(f"Path.{who}: t must be finite, got {shown(t)}")
        n = len(self.times)
        clamped = np.clip(t, self.times[0], self.times[-1])
        i = np.clip(np.searchsorted(self.times, clamped, side="right") - 1, 0, max(n - 2, 0))
        j = np.minimum(i + 1, n - 1)
        span = self.times[j] - self.times[i]
        u = np.divide(clamped - self.times[i], span, out=np.zeros_like(clamped), where=span > 0)
        return t, i, j, u, t.ndim == 0

    def pose(self, t) -> Pose:
        """The tool's pose at time ``t`` (seconds), clamped to ``[t0, t1]``.

        Args:
            t: a time, or an (N,) array of times.

        Returns:
            A single :class:`Pose` for a scalar ``t``, a batch of N for an array.

        Raises:
            ToolError: ``t`` is not finite or has more than one dimension.
        """
        _, i, j, u, _ = self._interval(t, "pose")
        position = self.positions[i] + u[..., None] * (self.positions[j] - self.positions[i])
        return Pose._trusted(position, slerp(self.rotations[i], self.rotations[j], u))

    def velocity(self, t) -> np.ndarray:
        """Linear velocity of the tool's origin at ``t``, model units per second: (3,), or (N, 3) for (N,) times.

        Constant over each interval between keys, the later interval's at a
        key (the last interval's at ``t1``), and zero outside ``[t0, t1]``
        where the tool rests (and for a one-key path).
        """
        t, i, j, _, _ = self._interval(t, "velocity")
        span = (self.times[j] - self.times[i])[..., None]
        step = self.positions[j] - self.positions[i]
        v = np.divide(step, span, out=np.zeros_like(step), where=span > 0)
        moving = (t >= self.times[0]) & (t <= self.times[-1])
        return np.where(moving[..., None], v, 0.0)

    def direction(self, t) -> np.ndarray:
        """Unit direction of travel at ``t`` (the contact force's ``T``): (3,) or (N, 3), zero where the tool rests."""
        v = self.velocity(t)
        speed = np.linalg.norm(v, axis=-1, keepdims=True)
        return np.divide(v, speed, out=np.zeros_like(v), where=speed > 0)

    def __repr__(self) -> str:
        travel = float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())
        return f"Path: {self.key_count} keys, t [{self.t0:.6g}, {self.t1:.6g}] s, travel {travel:.6g}"

    @classmethod
    def from_usd(cls, source, prim_path: str | None = None) -> Path:
        """The path of a time-sampled USD transform, so that an animation made in a DCC tool drives a tool.

        One key per time code at which the prim or an ancestor has a
        time-sampled ``xformOp`` (any op stack: translate, rotate*, orient,
        transform matrices...): the prim's local-to-world transform there, as
        USD composes it. Time codes become seconds through the stage's
        ``timeCodesPerSecond``; positions are in stage units, taken as model
        units. Between keys the path interpolates as :class:`Path` does,
        which agrees with USD at the keys (USD interpolates each op, e.g.
        Euler angles, separately in between).

        Args:
            source: a ``Usd.Prim``, a ``Usd.Stage`` or the path of a USD file.
            prim_path: for a stage or a file, the prim; default: the default
                prim, or the only root prim of a stage without one.

        Raises:
            SceneError: the file is missing or not USD, the prim is missing or
                not ``UsdGeom.Xformable``.
            ToolError: the transform has no time samples, scales, shears or
                mirrors at some time code (named), or ``prim_path`` was given
                with a prim, or ``source`` is none of the three.

        Example:
            >>> from pxr import Gf, Usd, UsdGeom
            >>> from warpblob.tools import Path
            >>> stage = Usd.Stage.CreateInMemory()
            >>> stage.SetTimeCodesPerSecond(24)
            >>> move = UsdGeom.Xform.Define(stage, "/Tool").AddTranslateOp()
            >>> _ = move.Set(Gf.Vec3d(0, 0, 0), 0), move.Set(Gf.Vec3d(1, 0, 0), 48)
            >>> Path.from_usd(stage, "/Tool")
            Path: 2 keys, t [0, 2] s, travel 1
        """
        from pxr import Usd, UsdGeom

        from ..io.usd import _root_prim, open_stage

        if isinstance(source, Usd.Prim):
            if prim_path is not None:
                raise ToolError(f"Path.from_usd: prim_path is for a stage or a file, got a prim and {prim_path!r}")
            if not source.IsValid():
                raise SceneError("Path.from_usd: the prim is not valid (expired or never defined)")
            prim = source
        else:
            if isinstance(source, Usd.Stage):
                stage = source
            elif isinstance(source, (str, os.PathLike)):
                stage = open_stage(os.fspath(source), "Path.from_usd")
            else:
                raise ToolError(
                    f"Path.from_usd: source must be a Usd.Prim, a Usd.Stage or a file path, got {shown(source)}"
                )
            prim = _root_prim(stage, stage.GetRootLayer().identifier, prim_path)
        xformable = UsdGeom.Xformable(prim)
        if not xformable:
            raise SceneError(f"Path.from_usd: prim <{prim.GetPath()}> is a {prim.GetTypeName() or 'typeless prim'}, "
                             "not a UsdGeom.Xformable")  # fmt: skip
        codes = set()
        up = prim
        while up and not up.IsPseudoRoot():
            # an animated parent moves the tool too; a static one has no samples to add
            above = UsdGeom.Xformable(up)
            if above:
                codes.update(above.GetTimeSamples())
            up = up.GetParent()
        if not codes:
            raise ToolError(f"Path.from_usd: <{prim.GetPath()}> has no time-sampled transform (on it or its ancestors)")
        codes = sorted(codes)
        # USD composes transforms one time code per call; this runs once per load, not per simulation step
        rows_major = np.array([xformable.ComputeLocalToWorldTransform(Usd.TimeCode(c)) for c in codes])
        pose = rigid_poses("Path.from_usd", np.transpose(rows_major, (0, 2, 1)),
                           lambda i: f"<{prim.GetPath()}> at time code {codes[i]:g}")  # fmt: skip
        return cls(np.array(codes) / prim.GetStage().GetTimeCodesPerSecond(), pose.position, pose.rotation)

    def to_usd(self, stage, prim_path: str):
        """Author the path as time-sampled ``translate`` and ``orient`` ops (double precision) on ``prim_path``.

        The prim is defined as an ``Xform`` if missing; an existing
        ``Xformable`` prim keeps its type and gets this op stack in place of
        its own. Keys go to time codes ``times * timeCodesPerSecond``, and the
        stage's start and end time codes are widened to cover them. The ops
        are the prim's local transform: :meth:`from_usd` reads world
        transforms, so the round trip is exact under an untransformed parent.

        Args:
            stage: a ``Usd.Stage``.
            prim_path: absolute prim path, e.g. ``"/World/Drill"``.

        Returns:
            The prim as a ``UsdGeom.Xformable``.

        Raises:
            ToolError: ``stage`` is not a ``Usd.Stage``.
            SceneError: ``prim_path`` is not an absolute prim path, or names a
                prim that is not ``Xformable``.

        Example:
            >>> from pxr import Usd
            >>> from warpblob.tools import Path
            >>> stage = Usd.Stage.CreateInMemory()
            >>> path = Path.line((0, 0, 0), (0, 0, -1), 2.0, align=True)
            >>> _ = path.to_usd(stage, "/Drill")
            >>> Path.from_usd(stage, "/Drill")
            Path: 2 keys, t [0, 2] s, travel 1
        """
        from pxr import Gf, Sdf, Usd, UsdGeom

        if not isinstance(stage, Usd.Stage):
            raise ToolError(f"Path.to_usd: stage must be a Usd.Stage, got {shown(stage)}")
        text = str(prim_path)
        if not (Sdf.Path.IsValidPathString(text) and Sdf.Path(text).IsAbsolutePath() and Sdf.Path(text).IsPrimPath()):
            raise SceneError(
                f"Path.to_usd: prim_path must be an absolute prim path like '/World/Tool', got {prim_path!r}"
            )
        prim = stage.GetPrimAtPath(text)
        xformable = UsdGeom.Xformable(prim) if prim else UsdGeom.Xform.Define(stage, text)
        if not xformable:
            raise SceneError(f"Path.to_usd: prim <{text}> is a {prim.GetTypeName() or 'typeless prim'}, not Xformable")
        prim = xformable.GetPrim()
        for name in ("xformOp:translate", "xformOp:orient"):
            # stale samples of an earlier path would otherwise survive under the new ops
            if prim.HasAttribute(name):
                prim.RemoveProperty(name)
        xformable.ClearXformOpOrder()
        translate = xformable.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
        orient = xformable.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
        codes = self.times * stage.GetTimeCodesPerSecond()
        # USD takes one time sample per call; paths are authored once, not per step
        for code, p, q in zip(codes.tolist(), self.positions.tolist(), self.rotations.tolist()):
            translate.Set(Gf.Vec3d(*p), code)
            orient.Set(Gf.Quatd(q[3], q[0], q[1], q[2]), code)
        if stage.HasAuthoredTimeCodeRange():
            stage.SetStartTimeCode(min(stage.GetStartTimeCode(), codes[0]))
            stage.SetEndTimeCode(max(stage.GetEndTimeCode(), codes[-1]))
        else:
            stage.SetStartTimeCode(codes[0])
            stage.SetEndTimeCode(codes[-1])
        return xformable
