"""Off-screen pictures of meshes: PyVista renders the mesh, matplotlib adds the title and the key."""

from __future__ import annotations

import os

__all__ = ["render_mesh"]


def render_mesh(
    mesh,
    path: str,
    *,
    title: str = "",
    window_size=(900, 700),
    view=(1.0, 1.0, 1.0),
    legend: dict | None = None,
) -> str:
    """Render a :class:`~warpblob.mesh.SurfaceMesh` with its colours to a PNG (atomically).

    Args:
        mesh: the mesh; its vertex colours are drawn as they are.
        path: the PNG file.
        title: text at the top left.
        window_size: (width, height) pixels.
        view: direction from the mesh's centre towards the camera (z is up).
        legend: label -> RGB colour in [0, 1], drawn as a key at the top right.

    Returns:
        ``path``.

    Example:
        >>> import os, tempfile, warpblob as wb
        >>> from warpblob._render import render_mesh
        >>> mesh = wb.polygonize(wb.scenes.peanut(), cellsize=0.2)
        >>> png = render_mesh(mesh, os.path.join(tempfile.mkdtemp(), "p.png"), legend={"shell": (0.86, 0.66, 0.42)})
        >>> open(png, "rb").read(4)
        b'\\x89PNG'
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pyvista as pv
    import vtk
    from matplotlib.patches import Patch

    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    pv.OFF_SCREEN = True
    # a light at the camera: every face turned towards the viewer is lit alike (the light kit's
    # key light from above leaves vertical faces, like the walls of a cut, in shadow)
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size), lighting="none")
    plotter.add_light(pv.Light(light_type="headlight"))
    plotter.set_background("white")
    if mesh.face_count:
        plotter.add_mesh(
            mesh.to_pyvista(), scalars="RGB", rgb=True, smooth_shading=True, ambient=0.4, diffuse=0.75, specular=0.15
        )
    plotter.view_vector(view, viewup=(0.0, 0.0, 1.0))
    plotter.camera.zoom(1.0)  # larger crops box-filling models (the towers) at the corners
    image = plotter.screenshot(return_img=True)
    plotter.close()

    # VTK's legend box sizes its text badly off screen: matplotlib draws the words
    width, height = window_size
    fig = plt.figure(figsize=(width / 100, height / 100), dpi=100)
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    ax.imshow(image)
    ax.set_axis_off()
    if title:
        ax.text(0.01, 0.99, title, transform=ax.transAxes, va="top", fontsize=11)
    if legend:
        handles = [Patch(facecolor=color, edgecolor="0.3", label=label) for label, color in legend.items()]
        ax.legend(handles=handles, loc="upper right", fontsize=11, framealpha=0.9, borderaxespad=0.8)
    tmp = path + ".tmp.png"
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, path)
    return path
