"""Pictures of a running scenario: the deformed surface in its colours, the contact area lit, the tool drawn.

PyVista renders off screen (``pv.OFF_SCREEN``): the embedded surface with its
model colours turned towards :data:`~warpblob.sim._contact.HIGHLIGHT` where
the tools push (:meth:`~warpblob.Simulation.surface_contact`), the samples
that penetrate as red points, each tool as a translucent steel mesh, from a
camera fixed for the whole run so frames compare.
"""

from __future__ import annotations

import os

import numpy as np

from ..sim._contact import highlight

__all__ = ["FrameCamera", "render_frame", "render_cut_frame"]

_TOOL_COLOR = (0.55, 0.58, 0.64)
_POINT_COLOR = (0.85, 0.1, 0.1)


def _plotter(window_size):
    """An off-screen plotter, white, lit by a headlight."""
    import pyvista as pv
    import vtk

    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size), lighting="none")
    plotter.add_light(pv.Light(light_type="headlight"))
    plotter.set_background("white")
    return plotter


def _save(plotter, camera, title: str, path: str) -> str:
    """Title, camera, then the PNG written atomically; the plotter closed. Returns ``path``."""
    if title:
        plotter.add_text(title, position="upper_left", font_size=11, color="black")
    camera.place(plotter)
    tmp = path + ".tmp.png"
    plotter.screenshot(tmp)
    plotter.close()
    os.replace(tmp, path)
    return path


class FrameCamera:
    """A camera fixed for a run: looking at ``center`` from ``direction``, framing a box of ``size``.

    Args:
        lower, upper: (3,) the box to frame (the rest volume and the tool's stroke).
        direction: (3,) from the box's centre towards the camera (z is up).
    """

    def __init__(self, lower, upper, direction=(1.0, -1.4, 0.9)):
        self.lower = np.asarray(lower, dtype=np.float64)
        self.upper = np.asarray(upper, dtype=np.float64)
        d = np.asarray(direction, dtype=np.float64)
        self.direction = d / np.linalg.norm(d)

    def place(self, plotter) -> None:
        center = 0.5 * (self.lower + self.upper)
        radius = 0.5 * float(np.linalg.norm(self.upper - self.lower))
        # a 30 degree view angle holds a sphere of this radius from 3.7 radii away; 2.7 crops only the box's corners
        plotter.camera_position = [tuple(center + 2.7 * radius * self.direction), tuple(center), (0.0, 0.0, 1.0)]
        plotter.camera.view_angle = 30.0


def render_frame(sim, path: str, camera: FrameCamera, *, title: str = "", window_size=(960, 720)) -> str:
    """Render the simulation's current state to a PNG (written atomically).

    Args:
        sim: a :class:`~warpblob.Simulation` with a bound surface.
        path: the PNG file.
        camera: the run's :class:`FrameCamera`.
        title: text at the top left.
        window_size: (width, height) pixels.

    Returns:
        ``path``.
    """
    import pyvista as pv

    plotter = _plotter(window_size)
    surface = sim.embedding.mesh
    colors = highlight(surface.colors, sim.surface_contact()) if sim.tools else surface.colors
    faces = np.column_stack([np.full(surface.face_count, 3), surface.faces]).ravel()
    body = pv.PolyData(sim.surface_positions().astype(np.float64), faces)
    body["RGB"] = (np.clip(colors, 0.0, 1.0) * 255).astype(np.uint8)
    plotter.add_mesh(body, scalars="RGB", rgb=True, smooth_shading=True, ambient=0.35, diffuse=0.75, specular=0.15)
    for index, record in enumerate(sim.tools):
        plotter.add_mesh(record.tool.to_pyvista(record.pose(sim.time)), color=_TOOL_COLOR, opacity=0.35,
                         smooth_shading=False, ambient=0.3)  # fmt: skip
        points = sim.contact_points(index)
        if len(points):
            plotter.add_points(points.astype(np.float64), color=_POINT_COLOR, point_size=7,
                               render_points_as_spheres=True)  # fmt: skip
    return _save(plotter, camera, title, path)


def render_cut_frame(sim, path: str, camera: FrameCamera, *, model=None, material_colors=None, title: str = "",
                     window_size=(960, 720)) -> str:  # fmt: skip
    """Render a simulation that cuts (built on a TetStructure) to a PNG: the tet mesh's boundary, cuts included.

    The boundary of the live tets at the current positions
    (:meth:`~warpblob.mesh.TetStructure.surface`), coloured by ``model``'s
    colour field at the rest positions (cut faces show the inside), the
    cutting tools (:attr:`~warpblob.Simulation.cutters`) drawn where their
    paths put them at ``sim.time``; written atomically.

    Args:
        sim: a :class:`~warpblob.Simulation` on a :class:`~warpblob.mesh.TetStructure`.
        path: the PNG file.
        camera: the run's :class:`FrameCamera`.
        model: BlobTree node for the colours (None: the simulation's model, else grey).
        material_colors: instead, a colour per material id (``{id: (r, g, b)}``): each face flat in its
            tet's tissue colour (a layered mesh's cut faces show its layers).
        title: text at the top left.
        window_size: (width, height) pixels.

    Returns:
        ``path``.
    """
    import pyvista as pv

    structure = sim._structure
    structure.set_positions(sim.positions)
    plotter = _plotter(window_size)
    if material_colors is not None:
        faces, owner = _boundary(np.asarray(structure.cell_nodes)[np.asarray(structure.cell_alive)])
        material = np.asarray(structure.cell_material)[np.asarray(structure.cell_alive)][owner]
        palette = np.array([material_colors.get(int(m), (0.7, 0.7, 0.7)) for m in range(int(material.max()) + 1)])
        body = pv.PolyData(sim.positions.astype(np.float64), np.column_stack([np.full(len(faces), 3), faces]).ravel())
        body.cell_data["RGB"] = (np.clip(palette[material], 0.0, 1.0) * 255).astype(np.uint8)
        plotter.add_mesh(body, scalars="RGB", rgb=True, smooth_shading=False, ambient=0.35, diffuse=0.75,
                         specular=0.1)  # fmt: skip
        surface = None
    else:
        surface = structure.surface(model=model if model is not None else sim.model)
    if surface is not None and surface.face_count:
        faces = np.column_stack([np.full(surface.face_count, 3), surface.faces]).ravel()
        body = pv.PolyData(surface.vertices.astype(np.float64), faces)
        body["RGB"] = (np.clip(surface.colors, 0.0, 1.0) * 255).astype(np.uint8)
        plotter.add_mesh(body, scalars="RGB", rgb=True, smooth_shading=False, ambient=0.35, diffuse=0.75,
                         specular=0.1)  # fmt: skip
    for cutter in sim.cutters:
        if cutter.path.t0 <= sim.time <= cutter.path.t1 + 0.25:
            plotter.add_mesh(cutter.tool.to_pyvista(cutter.path.pose(sim.time)), color=_TOOL_COLOR, opacity=0.5,
                             smooth_shading=False, ambient=0.3)  # fmt: skip
    return _save(plotter, camera, title, path)


def _boundary(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The faces of (T, 4) positive tets that no other tet shares, outward, and the tet each belongs to."""
    from ..mesh._tetmesh import TET_FACES

    faces = tets[:, TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    once = first[counts == 1]
    return faces[once], once // 4
