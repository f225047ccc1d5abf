"""The Python examples in README.md run as written."""

import os
import re

import numpy as np

import warpblob as wb
import warpblob.usd

README = os.path.join(os.path.dirname(__file__), "..", "README.md")


def test_readme_python_blocks_run(tmp_path, monkeypatch):
    blocks = re.findall(r"```python\n(.*?)```", open(README).read(), flags=re.S)
    assert len(blocks) >= 3
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("PYVISTA_OFF_SCREEN", "true")
    import pyvista as pv

    monkeypatch.setattr(pv, "OFF_SCREEN", True)
    namespace = {}
    for block in blocks:
        exec(compile(block, "README.md", "exec"), namespace)
    assert namespace["values"].shape == (100_000,) and np.any(namespace["values"] >= 0.5)
    assert namespace["mesh"].is_closed_manifold()
    assert (tmp_path / "model.usda").exists() and (tmp_path / "model_volume.usda").exists()
    assert namespace["q"].inverted_count == 0
    sim = namespace["sim"]
    assert (tmp_path / "tumor_drop.usdc").exists() and sim.time > 1.0
    assert np.all(sim.positions[:, 2] >= -1.6 - 1e-3)  # on the ground, not through it
    assert namespace["force"][2] > 0 and abs(namespace["change"]) < 0.01  # pushed down, volume kept
    pieces = namespace["pieces"]
    assert namespace["result"].components >= 8 and pieces.to_tetmesh().volumes().min() > 0
    assert wb.usd.load_tetmesh(str(tmp_path / "tumor_cut.usda")).tet_count == pieces.cell_count
    assert wb.usd.load_mesh(str(tmp_path / "tumor_cut_surface.usda")).is_cut.any()
    assert open(tmp_path / "tumor_cut.png", "rb").read(4) == b"\x89PNG"
    assert namespace["egg"].stats["components"] == 2 and (tmp_path / "craniotomy.usdc").exists()
    assert namespace["head"].stats["rigid"]["free"] >= 2  # the plugs (and the front's bone)


def test_the_drilling_page_example_runs(tmp_path, monkeypatch):
    """docs/drill.md's example runs as written (its own asserts check it)."""
    page = os.path.join(os.path.dirname(__file__), "..", "docs", "drill.md")
    blocks = re.findall(r"```python\n(.*?)```", open(page).read(), flags=re.S)
    assert len(blocks) == 1
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[0], "docs/drill.md", "exec"), {})

