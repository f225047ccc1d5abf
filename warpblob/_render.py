"""Off-screen pictures of meshes with PyVista (the only place VTK rendering is used)."""

from __future__ import annotations

import os

__all__ = ["render_mesh"]


def render_mesh(mesh, path: str, *, title: str = "", window_size=(900, 700)) -> str:
    """Render a :class:`~warpblob.mesh.SurfaceMesh` with its colours to a PNG (atomically)."""
    import pyvista as pv
    import vtk

    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    plotter.set_background("white")
    if mesh.face_count:
        plotter.add_mesh(mesh.to_pyvista(), scalars="RGB", rgb=True, smooth_shading=True, specular=0.3)
    if title:
        plotter.add_text(title, font_size=10, color="black")
    plotter.view_isometric()
    plotter.camera.zoom(1.2)
    tmp = path + ".tmp.png"
    plotter.screenshot(tmp)
    plotter.close()
    os.replace(tmp, path)
    return path
