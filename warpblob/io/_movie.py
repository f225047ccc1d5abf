"""Pictures of animated USD stages: PNG frames and an animated GIF rendered off screen, an interactive viewer.

What is drawn at a time code is what a viewer draws: every ``UsdGeom.Mesh``
whose computed visibility is not ``invisible`` and whose purpose is not
``guide`` (so a recording's TetMesh, a guide, is left out and its piece
meshes are drawn), placed by its local-to-world transform (the tools move),
coloured by its vertex ``displayColor`` (the model's colours, the cut faces
included: those ``primvars:isCut`` marks a little darker, so the cut walls
stand out), else its constant ``displayColor``, else grey. The camera is set
once from the box of every frame, so the pictures do not jump.
"""

from __future__ import annotations

import concurrent.futures
import functools
import os
import pathlib

import numpy as np

from .._errors import SceneError

__all__ = ["render_frames", "render_gif", "stage_summary", "view"]

#: files ``view`` opens as static meshes through PyVista
_MESH_FILES = (".stl", ".obj", ".ply", ".vtk", ".vtp", ".vtu")
_USD_FILES = (".usd", ".usda", ".usdc", ".usdz")
#: colour factor of the faces ``primvars:isCut`` marks, in pictures
CUT_SHADE = 0.72


def _open(path, who):
    from .usd import open_stage

    return open_stage(path, who)


def stage_summary(path) -> dict:
    """Counts and time range of a USD stage: what ``warpblob view`` prints without a display.

    Returns:
        ``{"path", "prims", "meshes", "tetmeshes", "xforms", "materials", "start", "end",
        "time_codes_per_second", "frames_per_second", "up_axis", "meters_per_unit",
        "default_prim", "animated"}`` (``animated``: attributes with more than one time sample).

    Example:
        >>> import os, tempfile, warpblob as wb, warpblob.usd
        >>> path = wb.usd.save_mesh(wb.polygonize(wb.Point((0, 0, 0), 1.0), cellsize=0.3),
        ...                         os.path.join(tempfile.mkdtemp(), "ball.usda"))
        >>> wb.usd.stage_summary(path)["meshes"]
        1
    """
    from pxr import UsdGeom, UsdShade

    stage = _open(path, "stage_summary")
    counts = {"prims": 0, "meshes": 0, "tetmeshes": 0, "xforms": 0, "materials": 0, "animated": 0}
    for prim in stage.Traverse():
        counts["prims"] += 1
        counts["meshes"] += prim.IsA(UsdGeom.Mesh)
        counts["tetmeshes"] += prim.IsA(UsdGeom.TetMesh)
        counts["xforms"] += prim.IsA(UsdGeom.Xform)
        counts["materials"] += prim.IsA(UsdShade.Material)
        counts["animated"] += sum(a.GetNumTimeSamples() > 1 for a in prim.GetAttributes())
    default = stage.GetDefaultPrim()
    return {
        "path": os.fspath(path),
        **counts,
        "start": stage.GetStartTimeCode(),
        "end": stage.GetEndTimeCode(),
        "time_codes_per_second": stage.GetTimeCodesPerSecond(),
        "frames_per_second": stage.GetFramesPerSecond(),
        "up_axis": str(UsdGeom.GetStageUpAxis(stage)),
        "meters_per_unit": UsdGeom.GetStageMetersPerUnit(stage),
        "default_prim": str(default.GetPath()) if default else None,
    }


def _meshes_at(stage, code) -> list:
    """(points (V, 3) world, faces (F, 3), colours (V, 3)) of every drawn Mesh at ``code``."""
    from pxr import UsdGeom

    out = []
    cache = UsdGeom.XformCache(code)
    for prim in stage.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        if mesh.ComputeVisibility(code) == UsdGeom.Tokens.invisible or mesh.ComputePurpose() == UsdGeom.Tokens.guide:
            continue
        points = mesh.GetPointsAttr().Get(code)
        counts = mesh.GetFaceVertexCountsAttr().Get(code)
        indices = mesh.GetFaceVertexIndicesAttr().Get(code)
        if not points or not counts or not indices:
            continue
        v = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        counts = np.asarray(counts, dtype=np.int64)
        idx = np.asarray(indices, dtype=np.int64)
        if np.all(counts == 3):
            faces = idx.reshape(-1, 3)
        else:  # fan-triangulate polygons
            starts = np.r_[0, np.cumsum(counts)[:-1]]
            tris = [[idx[s], idx[s + k], idx[s + k + 1]] for s, n in zip(starts, counts) for k in range(1, n - 1)]
            faces = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        m = np.array(cache.GetLocalToWorldTransform(prim), dtype=np.float64)  # row vectors: p' = p M
        v = v @ m[:3, :3] + m[3, :3]
        color = mesh.GetDisplayColorPrimvar().Get(code) if mesh.GetDisplayColorPrimvar().HasValue() else None
        c = np.asarray(color, dtype=np.float32).reshape(-1, 3) if color is not None else np.zeros((0, 3), np.float32)
        if len(c) != len(v):
            c = np.broadcast_to(c[0] if len(c) else np.float32([0.8, 0.8, 0.8]), v.shape)
        c = np.clip(c, 0, 1)
        cut = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("isCut")
        cut = np.asarray(cut.Get(code), dtype=bool) if cut and cut.HasValue() else None
        if cut is not None and len(cut) == len(faces) and cut.any() and CUT_SHADE != 1.0:
            # the faces a blade made, darker: the cut walls stand out from the outside
            out.append((v, faces[~cut], c))
            out.append((v, faces[cut], c * np.float32(CUT_SHADE)))
        else:
            out.append((v, faces, c))
    return out


def _poly(v, faces, colors):
    import pyvista as pv

    cells = np.column_stack([np.full(len(faces), 3, dtype=np.int64), faces]).ravel()
    poly = pv.PolyData(v, cells)
    poly.point_data["RGB"] = (np.asarray(colors) * 255).astype(np.uint8)
    return poly


def _codes(stage, frames: int | None) -> np.ndarray:
    start, end = stage.GetStartTimeCode(), stage.GetEndTimeCode()
    codes = np.arange(np.floor(start), np.floor(end) + 1, dtype=np.float64) if end > start else np.array([start])
    if frames is not None and len(codes) > frames:
        codes = codes[np.unique(np.linspace(0, len(codes) - 1, frames).round().astype(int))]
    return codes


def _bounds(stage, codes) -> np.ndarray:
    """(2, 3) box of every drawn mesh over ``codes`` (their extents, as USD's bounding box cache computes it)."""
    from pxr import Usd, UsdGeom

    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    for code in codes:
        cache = UsdGeom.BBoxCache(Usd.TimeCode(float(code)), [UsdGeom.Tokens.default_, UsdGeom.Tokens.render,
                                                               UsdGeom.Tokens.proxy])  # fmt: skip
        box = cache.ComputeWorldBound(stage.GetPseudoRoot()).ComputeAlignedRange()
        if not box.IsEmpty():
            low = np.minimum(low, np.array(box.GetMin()))
            high = np.maximum(high, np.array(box.GetMax()))
    if not np.isfinite(low).all():
        return np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    return np.array([low, high])


def render_frames(stage_path, out_dir, *, frames: int | None = 60, window_size=(640, 480), view=(1.0, -1.4, 0.8),
                  prefix: str | None = None, progress: bool | None = None) -> list[pathlib.Path]:  # fmt: skip
    """Render time codes of a USD stage off screen to PNG files ``<out_dir>/<prefix>_<code>.png``.

    Args:
        stage_path: a ``.usd``/``.usda``/``.usdc`` file.
        out_dir: folder for the PNGs (made if missing).
        frames: at most this many time codes, evenly spread over start..end (None: every integer code).
        window_size: (width, height) pixels.
        view: direction from the scene's centre towards the camera (z is up).
        prefix: file name prefix (default: the stage's stem).
        progress: show a bar on a terminal (default: for more than 10 frames).

    Returns:
        The PNG paths, in time order.

    Raises:
        SceneError: the stage cannot be read.
    """
    import imageio.v3 as iio
    import pyvista as pv
    import vtk
    from pxr import Usd

    from .._parallel import submit
    from .._progress import progress as bar

    stage = _open(stage_path, "render_frames")
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    prefix = prefix or pathlib.Path(stage_path).stem
    codes = _codes(stage, frames)
    low, high = _bounds(stage, codes)
    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size), lighting="none")
    plotter.add_light(pv.Light(light_type="headlight"))
    plotter.set_background("white")
    center, size = 0.5 * (low + high), float(np.linalg.norm(high - low))
    direction = np.asarray(view, dtype=np.float64) / np.linalg.norm(view)
    plotter.camera.focal_point = center.tolist()
    plotter.camera.position = (center + 1.6 * max(size, 1e-6) * direction).tolist()  # the box in a 30 degree view
    plotter.camera.up = (0.0, 0.0, 1.0)
    plotter.camera.view_angle = 30.0
    fps = stage.GetTimeCodesPerSecond()
    paths = []
    show = progress if progress is not None else len(codes) > 10

    def write(image, path):
        tmp = path.with_name(path.name + ".tmp.png")
        iio.imwrite(tmp, image)
        os.replace(tmp, path)

    # the PNGs are encoded on a pool thread (zlib lets go of the GIL) while the next frame renders
    pending = []
    try:
        actors = []
        for code in bar(codes, desc="render", total=len(codes)) if show else codes:
            for actor in actors:  # render=False: one render per frame, the screenshot's
                plotter.remove_actor(actor, render=False)
            actors = [plotter.add_mesh(_poly(v, f, c), scalars="RGB", rgb=True, smooth_shading=True, ambient=0.4,
                                       diffuse=0.75, specular=0.15, reset_camera=False, render=False)
                      for v, f, c in _meshes_at(stage, Usd.TimeCode(float(code)))]  # fmt: skip
            actors.append(plotter.add_text(f"t = {code / fps:.3f} s  (time code {code:g})", font_size=9,
                                           color="black", render=False))  # fmt: skip
            plotter.camera.clipping_range = (1e-3 * size, 10.0 * size)
            plotter.render()
            image = plotter.screenshot(return_img=True)
            path = out / f"{prefix}_{round(code):05d}.png"
            pending += submit(functools.partial(write, image, path), 1)
            paths.append(path)
    finally:
        plotter.close()
        concurrent.futures.wait(pending)
    for job in pending:
        job.result()  # a failed write raises here
    return paths


def render_gif(stage_path, out_gif, *, frames: int | None = 60, fps: float | None = None, frames_dir=None,
               window_size=(640, 480), view=(1.0, -1.4, 0.8), progress: bool | None = None) -> pathlib.Path:  # fmt: skip
    """An animated GIF of a USD stage (and its PNG frames), rendered off screen with PyVista, written by imageio.

    Args:
        stage_path: a ``.usd``/``.usda``/``.usdc`` file.
        out_gif: the ``.gif`` file (written atomically).
        frames: at most this many time codes, evenly spread (None: every integer code).
        fps: frames per second of the GIF (default: as many as it plays the
            stage's time in real time, capped at 50, GIF's limit).
        frames_dir: folder for the PNG frames (default: ``<out_gif stem>_frames`` beside the GIF).
        window_size, view, progress: as :func:`render_frames`.

    Returns:
        ``out_gif`` as a :class:`pathlib.Path`.

    Raises:
        SceneError: a suffix other than ``.gif``, a missing folder, or an unreadable stage.

    Example:
        >>> import os, tempfile, warpblob as wb, warpblob.usd
        >>> d = tempfile.mkdtemp()
        >>> s = wb.TetStructure.from_tetmesh(wb.mesh.box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2)))
        >>> with wb.usd.Recorder(os.path.join(d, "box.usdc")) as rec:
        ...     _ = rec.add(s)
        ...     rec.frame()
        ...     _ = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.4, 0.5, 0.5), (1, 0.2, 0), 2.0))
        ...     rec.frame()
        >>> wb.usd.render_gif(rec.path, os.path.join(d, "box.gif")).read_bytes()[:3]
        b'GIF'
    """
    import imageio.v3 as iio

    target = pathlib.Path(out_gif)
    if target.suffix.lower() != ".gif":
        raise SceneError(f"render_gif: out_gif must end in .gif, got {str(out_gif)!r}")
    if not target.parent.is_dir():
        raise SceneError(f"render_gif: folder {str(target.parent)!r} of {str(out_gif)!r} does not exist")
    folder = pathlib.Path(frames_dir) if frames_dir is not None else target.with_name(target.stem + "_frames")
    pngs = render_frames(stage_path, folder, frames=frames, window_size=window_size, view=view,
                         prefix=target.stem, progress=progress)  # fmt: skip
    stage = _open(stage_path, "render_gif")
    codes = _codes(stage, frames)
    if fps is None:
        span = (codes[-1] - codes[0]) / stage.GetTimeCodesPerSecond() if len(codes) > 1 else 1.0
        fps = min(50.0, max(1.0, (len(codes) - 1) / span)) if span > 0 else 10.0
    images = np.stack([iio.imread(p) for p in pngs])
    tmp = target.with_name(f".{target.name}.tmp.gif")
    try:
        iio.imwrite(tmp, images, extension=".gif", duration=1000.0 / float(fps), loop=0)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()
    return target


def headless() -> bool:
    """True where no window can open: PyVista set off screen, or no X11/Wayland display on Linux."""
    import sys

    if os.environ.get("PYVISTA_OFF_SCREEN", "").lower() in ("1", "true"):
        return True
    if sys.platform.startswith("linux"):
        return not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    return False


def view(path, *, window: bool | None = None) -> str:
    """Open a USD stage or a mesh file in an interactive PyVista window with a time slider.

    Without a display (or with ``window=False``) nothing opens: the returned
    text says how to open the file in usdview and summarizes it (prims, time
    range), and the caller prints it.

    Args:
        path: a ``.usd``/``.usda``/``.usdc``/``.usdz`` stage or a ``.stl``/``.obj``/``.ply``/``.vtk``/``.vtp``/``.vtu`` mesh.
        window: open a window (default: when a display exists).

    Returns:
        The text printed (empty after a window was shown).

    Raises:
        SceneError: a missing file, an unknown suffix, or an unreadable file.
    """
    source = os.fspath(path)
    suffix = os.path.splitext(source)[1].lower()
    if suffix not in _USD_FILES + _MESH_FILES:
        raise SceneError(f"view: {source}: unknown file type {suffix!r}; expected one of {', '.join(_USD_FILES + _MESH_FILES)}")
    if not os.path.isfile(source):
        raise SceneError(f"view: {source}: no such file")
    show = (not headless()) if window is None else window
    if suffix in _MESH_FILES:
        import pyvista as pv

        data = pv.read(source)
        if not show:
            return (f"{source}: {data.n_points} points, {data.n_cells} cells, bounds {np.round(data.bounds, 4).tolist()}\n"
                    f"no display: open it with `warpblob view {source}` where one exists, or in ParaView")  # fmt: skip
        plotter = pv.Plotter(title=source)
        plotter.add_mesh(data, show_edges=data.n_cells < 20000)
        plotter.show()
        return ""
    s = stage_summary(source)
    if not show:
        return (f"{source}: {s['prims']} prims ({s['meshes']} meshes, {s['tetmeshes']} tet meshes, {s['xforms']} "
                f"xforms, {s['materials']} materials), time codes {s['start']:g}..{s['end']:g} at "
                f"{s['time_codes_per_second']:g} per second, {s['animated']} animated attributes, "
                f"up axis {s['up_axis']}, {s['meters_per_unit']:g} m per unit\n"
                f"no display: open it in usdview (`usdview {source}`, then play with the timeline's play button "
                f"or Ctrl+Right), in Blender (File > Import > Universal Scene Description) or in Omniverse")  # fmt: skip
    _interactive(source)
    return ""


def _interactive(source: str) -> None:  # pragma: no cover - needs a display
    import pyvista as pv
    from pxr import Usd

    stage = _open(source, "view")
    codes = _codes(stage, None)
    low, high = _bounds(stage, codes[[0, -1]] if len(codes) > 1 else codes)
    plotter = pv.Plotter(title=source)
    fps = stage.GetTimeCodesPerSecond()

    def show(value):
        code = float(codes[int(np.argmin(np.abs(codes - value)))])
        plotter.clear_actors()
        for v, f, c in _meshes_at(stage, Usd.TimeCode(code)):
            plotter.add_mesh(_poly(v, f, c), scalars="RGB", rgb=True, smooth_shading=True, reset_camera=False)
        plotter.add_text(f"t = {code / fps:.3f} s", font_size=10)

    show(codes[0])
    plotter.reset_camera(bounds=[low[0], high[0], low[1], high[1], low[2], high[2]])
    if len(codes) > 1:
        plotter.add_slider_widget(show, [float(codes[0]), float(codes[-1])], value=float(codes[0]), title="time code",
                                  fmt="%.0f", pointa=(0.25, 0.92), pointb=(0.75, 0.92))  # fmt: skip
    plotter.show()
