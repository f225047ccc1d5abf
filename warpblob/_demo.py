"""The whole pipeline in one run (``warpblob demo``): model, polygonize, tetrahedralize, probe, cut, drill, slice.

:func:`run_pipeline` plays the stages after the models' own pictures (which
``cli.cmd_demo`` makes: field slices, meshes, Monte Carlo volumes):

1. **tetrahedralize** the tumor, the eggshell and the layered head (one
   conforming mesh of its tissues, :func:`warpblob.scenes.head_materials`)
   by isosurface stuffing; ``tet_quality.png`` holds their
   dihedral-angle and aspect-ratio histograms;
2. **probe** the tumor (:func:`warpblob.scenarios.probe_tumor`);
3. **cut** the tumor three times with a scalpel (:func:`warpblob.scenarios.cut_tumor`);
4. **drill** the eggshell (:func:`warpblob.scenarios.drill_eggshell`);
5. **slice** the mug through its handle (:func:`warpblob.slice.slice`);

each simulation recorded as its own animated stage (``<name>.usdc``,
:class:`warpblob.usd.Recorder` through :meth:`~warpblob.Simulation.record`)
and rendered to an animated GIF (``<name>.gif``, its PNG frames in
``<name>_frames/``). :func:`compose_stage` then writes
``warpblob_demo.usdc``: the polygonized models at ``/Demo/<model>`` and
every recorded scenario at ``/Demo/Scenarios/<name>``, side by side, all
playing from time 0 (one flattened, self-contained stage). Every figure goes
into the summary the caller writes.
"""

from __future__ import annotations

import os
import pathlib
import time

import numpy as np

__all__ = ["run_pipeline", "compose_stage", "quality_histograms", "SIZES"]

#: per stage, the cell size (model units) and steps of a full run and of ``--quick``
SIZES = {
    "full": {"tumor": 0.2, "eggshell": 0.12, "head": 0.12, "probe": (0.25, 120), "cut": 0.2, "drill": 0.12,
             "mug": 0.05, "gif_frames": 36},
    "quick": {"tumor": 0.4, "eggshell": 0.14, "head": 0.3, "probe": (0.5, 30), "cut": 0.4, "drill": 0.14,
              "mug": 0.1, "gif_frames": 6},
}  # fmt: skip
#: camera directions of the GIFs (from the scene towards the camera, z up)
_VIEWS = {"probe_tumor": (1.0, -1.6, 1.1), "cut_tumor": (1.0, -1.5, 1.0), "drill_eggshell": (0.7, -1.0, -0.9)}


def quality_histograms(meshes: dict, path: str, qualities: dict | None = None) -> str:
    """One PNG of the tet meshes' quality: per mesh, the histogram of all dihedral angles and of the aspect ratio.

    Args:
        meshes: name -> :class:`~warpblob.TetMesh`.
        path: the PNG file (written atomically).
        qualities: name -> its :class:`~warpblob.TetQuality` where already measured (else measured here).

    Returns:
        ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_angle, ax_ratio) = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, mesh in meshes.items():
        q = qualities[name] if qualities and name in qualities else mesh.quality()
        ax_angle.hist(q.tet_dihedral.ravel(), bins=90, range=(0, 180), histtype="step", density=True,
                      label=f"{name} ({mesh.tet_count:,} tets, {q.dihedral_min:.1f}-{q.dihedral_max:.1f} deg)")  # fmt: skip
        ratio = q.tet_aspect_ratio[np.isfinite(q.tet_aspect_ratio)]
        ax_ratio.hist(ratio, bins=60, range=(1.0, 4.0), histtype="step", density=True, label=name)
    ax_angle.set(xlabel="dihedral angle (degrees)", ylabel="density", title="dihedral angles, all six per tet")
    ax_ratio.set(xlabel="aspect ratio CR / (3 IR) (1: regular)", title="aspect ratio per tet")
    for ax in (ax_angle, ax_ratio):
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
    return path


def _tetrahedralize(out: pathlib.Path, sizes: dict, device) -> tuple[dict, dict]:
    from . import scenes
    from .tetrahedralize import tetrahedralize

    meshes, info, qualities = {}, {}, {}
    jobs = [("tumor", scenes.tumor(), sizes["tumor"], {}), ("eggshell", scenes.eggshell(), sizes["eggshell"], {})]
    layers = scenes.head_materials()
    jobs.append(("head", layers["skull"], sizes["head"], {"materials": layers}))
    for name, model, h, options in jobs:
        t0 = time.perf_counter()
        mesh = tetrahedralize(model, cellsize=h, device=device, **options)
        seconds = time.perf_counter() - t0
        q = qualities[name] = mesh.quality()
        meshes[name] = mesh
        info[name] = {"cellsize": h, "seconds": round(seconds, 3), "tets": mesh.tet_count, "nodes": mesh.node_count,
                      "dihedral_min": round(q.dihedral_min, 2), "dihedral_max": round(q.dihedral_max, 2),
                      "aspect_ratio_max": round(q.aspect_ratio_max, 3), "volume": round(mesh.volume(), 5)}  # fmt: skip
        if mesh.material is not None:
            ids, counts = np.unique(mesh.material, return_counts=True)
            info[name]["tets_per_material"] = {int(i): int(c) for i, c in zip(ids, counts)}
    quality_histograms(meshes, str(out / "tet_quality.png"), qualities)
    return meshes, info


def _record(sim, out: pathlib.Path, name: str, steps: int, sizes: dict) -> dict:
    """Run ``steps`` steps of ``sim`` into ``<name>.usdc`` and its GIF; the figures of the run."""
    from .io._movie import render_gif

    rest = sim.volume()
    t0 = time.perf_counter()
    stage = sim.record(out / f"{name}.usdc", steps, progress=False)
    seconds = time.perf_counter() - t0
    t1 = time.perf_counter()
    gif = render_gif(stage, out / f"{name}.gif", frames=sizes["gif_frames"], view=_VIEWS.get(name, (1, -1.4, 0.8)),
                     progress=False)  # fmt: skip
    figures = {"stage": stage.name, "gif": gif.name, "steps": steps, "seconds": round(seconds, 3),
               "ms_per_step": round(1e3 * seconds / steps, 2), "render_seconds": round(time.perf_counter() - t1, 3),
               "tets": sim.tet_count, "nodes": sim.node_count,
               "volume_change_percent": round(100.0 * (sim.volume() - rest) / rest, 4),
               "pieces": int(sim.stats.get("components", 1)),
               "cg_iterations_per_step": round(sim.stats["cg_iterations_total"] / steps, 2)}  # fmt: skip
    if sim.cutters:
        from .scenarios import drill_steps

        rows = drill_steps(sim)
        ms = [r["ms"]["total"] for r in rows]
        figures["cuts"] = {"count": len(rows), "tets_cut": sum(r["tets_cut"] for r in rows),
                           "tets_added": sum(r["tets_added"] for r in rows),
                           "cut_ms_median": round(float(np.median(ms)), 2) if ms else None,
                           "cut_ms_max": round(float(np.max(ms)), 2) if ms else None}  # fmt: skip
    return figures


def _slice(out: pathlib.Path, sizes: dict, device) -> dict:
    import warpblob.usd as usd

    from . import scenes
    from .polygonize import polygonize
    from .slice import slice as slice_mesh
    from .slice._picture import render_pieces

    mug = scenes.mug()
    t0 = time.perf_counter()
    cup = polygonize(mug, cellsize=sizes["mug"], device=device)
    t1 = time.perf_counter()
    below, above = slice_mesh(cup, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), model=mug, device=device)
    t2 = time.perf_counter()
    render_pieces([below, above], str(out / "slice_mug.png"), normal=(0.0, 1.0, 0.0),
                  title=f"mug sliced through its handle: {below.face_count + above.face_count:,} triangles")  # fmt: skip
    usd.save_mesh(below, out / "slice_mug_below.usda")
    usd.save_mesh(above, out / "slice_mug_above.usda")
    return {"cellsize": sizes["mug"], "polygonize_seconds": round(t1 - t0, 3), "slice_seconds": round(t2 - t1, 4),
            "closed": [below.is_closed_manifold(), above.is_closed_manifold()],
            "section_loops": int(below.stats.get("section_loops", 0)), "picture": "slice_mug.png",
            "halves": ["slice_mug_below.usda", "slice_mug_above.usda"]}  # fmt: skip


def run_pipeline(out, *, quick: bool = False, device=None, progress: bool = True) -> dict:
    """Tetrahedralize, probe, cut, drill and slice (module docstring), writing into ``out``; the figures.

    Args:
        out: an existing folder.
        quick: small sizes and few frames (a test run of well under a minute).
        device: Warp device.
        progress: a bar over the stages.

    Returns:
        ``{"tetrahedralize": ..., "probe_tumor": ..., "cut_tumor": ..., "drill_eggshell": ..., "slice": ...,
        "seconds": {stage: s}}``, and ``"stages"``: the recorded stage files by scenario.
    """
    from ._progress import progress as bar
    from .scenarios import cut_tumor, drill_eggshell, probe_tumor, total_steps

    out = pathlib.Path(out)
    sizes = SIZES["quick" if quick else "full"]
    summary, seconds = {}, {}

    def probe():
        h, steps = sizes["probe"]
        return _record(probe_tumor(h, steps, device=device), out, "probe_tumor", steps, sizes)

    def cutting():
        sim = cut_tumor(sizes["cut"], device=device)
        return _record(sim, out, "cut_tumor", total_steps(sim), sizes)

    def drilling():
        sim = drill_eggshell(sizes["drill"], device=device)
        return _record(sim, out, "drill_eggshell", total_steps(sim), sizes)

    stages = [("tetrahedralize", lambda: _tetrahedralize(out, sizes, device)[1]), ("probe_tumor", probe),
              ("cut_tumor", cutting), ("drill_eggshell", drilling), ("slice", lambda: _slice(out, sizes, device))]  # fmt: skip
    for name, run in bar(stages, desc="pipeline", total=len(stages)) if progress else stages:
        t0 = time.perf_counter()
        summary[name] = run()
        seconds[name] = round(time.perf_counter() - t0, 2)
    summary["seconds"] = seconds
    summary["stages"] = {name: summary[name]["stage"] for name in ("probe_tumor", "cut_tumor", "drill_eggshell")}
    return summary


def compose_stage(path, meshes: dict, scenarios: dict) -> pathlib.Path:
    """Write one self-contained animated stage: the polygonized ``meshes`` and the recorded ``scenarios``.

    The models sit at ``/Demo/<name>/surface`` on a grid; each scenario stage
    (name -> file) is referenced at ``/Demo/Scenarios/<name>`` and moved to
    the right of the models, the scenarios side by side; the composed stage
    is flattened (the references resolved) and written atomically, its time
    range the longest scenario's.

    Returns:
        ``path`` as a :class:`pathlib.Path`.
    """
    from .io.usd import export_atomically

    path = pathlib.Path(path)
    # composed in a layer beside the scenario files, so that their relative paths resolve while
    # the references are added (an in-memory layer would warn that it cannot open them)
    anchor = path.parent / f".{path.stem}.compose.usda"
    try:
        flat = _compose(anchor, path, meshes, scenarios)
    finally:
        anchor.unlink(missing_ok=True)
    flat.defaultPrim = "Demo"
    return export_atomically(flat, path, "demo")


def _compose(anchor: pathlib.Path, path: pathlib.Path, meshes: dict, scenarios: dict):
    """:func:`compose_stage`'s stage, authored in the layer file ``anchor`` and flattened into one layer."""
    from pxr import Gf, Usd, UsdGeom

    from .io.usd import author_mesh, new_stage

    stage = new_stage(default_prim="Demo", path=anchor)
    columns = 3
    sizes = [np.ptp(m.vertices, axis=0)[:2].max() for m in meshes.values() if m.vertex_count]
    pitch = 1.2 * float(max(sizes, default=1.0))
    for k, (name, mesh) in enumerate(meshes.items()):
        xform = UsdGeom.Xform.Define(stage, f"/Demo/{name}")
        center = mesh.vertices.mean(axis=0) if mesh.vertex_count else np.zeros(3)
        offset = np.array([(k % columns) * pitch, -(k // columns) * pitch, 0.0]) - np.array([center[0], center[1], 0.0])
        xform.AddTranslateOp().Set(Gf.Vec3d(*(float(x) for x in offset)))
        author_mesh(stage, f"/Demo/{name}/surface", mesh)
    x = float(columns * pitch + pitch)
    start, end, rate = 0.0, 0.0, 60.0
    for name, file in scenarios.items():
        source = Usd.Stage.Open(str(file))
        end = max(end, source.GetEndTimeCode())
        rate = source.GetTimeCodesPerSecond()
        box = UsdGeom.BBoxCache(source.GetStartTimeCode(), [UsdGeom.Tokens.default_]).ComputeWorldBound(
            source.GetDefaultPrim()).ComputeAlignedRange()  # fmt: skip
        width = float(box.GetSize()[0]) if not box.IsEmpty() else pitch
        lo = box.GetMin() if not box.IsEmpty() else Gf.Vec3d(0.0)
        prim = UsdGeom.Xform.Define(stage, f"/Demo/Scenarios/{name}")
        prim.AddTranslateOp().Set(Gf.Vec3d(x - float(lo[0]), 0.0, 0.0))
        prim.GetPrim().GetReferences().AddReference(os.path.relpath(file, path.parent),
                                                    source.GetDefaultPrim().GetPath())  # fmt: skip
        x += width + 0.5 * pitch
    stage.SetStartTimeCode(start)
    stage.SetEndTimeCode(end)
    stage.SetTimeCodesPerSecond(rate)
    stage.SetFramesPerSecond(rate)
    return stage.Flatten()

