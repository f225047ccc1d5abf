"""The ``warpblob cut`` command: the stage it writes, what it prints, the picture, its errors."""

import re

import numpy as np
import pytest

import warpblob as wb
import warpblob.usd
from warpblob.cli import _parser, main

PLANES = ["0,0,0.05,0,0,1", "0.03,0,0,1,0,0", "0,0,0,1,1,0"]
#: the cut snaps within this fraction of an edge
SNAP = 0.2


def _run(argv) -> int:
    """Parse and run one command in this process, letting WarpblobError through (``main`` would print it)."""
    args = _parser().parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def cut_run(tmp_path_factory):
    import contextlib
    import io

    out = tmp_path_factory.mktemp("cut")
    argv = ["cut", "tumor", "--cellsize", "0.2", "--out", str(out / "cut.usda"), "--png", str(out / "cut.png")]
    for plane in PLANES:
        argv += ["--plane", plane]
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert _run(argv) == 0
    return out, text.getvalue()


def _planes():
    values = [np.array([float(x) for x in p.split(",")]) for p in PLANES]
    return [(v[:3], v[3:] / np.linalg.norm(v[3:])) for v in values]


def test_stage_reads_back_with_every_piece_on_one_side(cut_run):
    from pxr import Usd, UsdGeom

    out, text = cut_run
    stage = Usd.Stage.Open(str(out / "cut.usda"))
    assert stage.GetDefaultPrim().GetPath() == "/Cut"
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    volume = wb.usd.load_tetmesh(str(out / "cut.usda"), prim_path="/Cut/Volume")
    original = wb.tetrahedralize(wb.scenes.tumor(), cellsize=0.2)
    # the cut adds tets, loses no volume and inverts none
    assert volume.tet_count > original.tet_count
    assert abs(volume.volume() - original.volume()) <= 1e-6 * original.volume()
    assert volume.volumes().min() > 0
    pieces = np.asarray(UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Cut/Volume")).GetPrimvar("piece").Get())
    assert pieces.shape == (volume.tet_count,)
    # the printed tet count and pieces are the stage's
    last = re.search(r"(\d+) tets, (\d+) nodes in (\d+) pieces", text)
    assert int(last.group(1)) == volume.tet_count and int(last.group(3)) == len(np.unique(pieces))
    # three planes through the middle: at least eight pieces, each on one side of every plane (within the snap)
    assert len(np.unique(pieces)) >= 8
    p = volume.nodes[volume.tets].astype(np.float64)
    longest = max(np.linalg.norm(p[:, i] - p[:, j], axis=1).max() for i in range(4) for j in range(i))
    centre = p.mean(axis=1)
    for origin, normal in _planes():
        d = (centre - origin) @ normal
        for k in np.unique(pieces):
            dk = d[pieces == k]
            assert dk.min() >= -SNAP * longest or dk.max() <= SNAP * longest


def test_surface_carries_cut_faces_and_pieces(cut_run):
    from pxr import Usd, UsdGeom

    out, _ = cut_run
    surface = wb.usd.load_mesh(str(out / "cut.usda"), prim_path="/Cut/Surface")
    assert surface.is_cut is not None and surface.is_cut.shape == (surface.face_count,)
    assert 0 < surface.is_cut.sum() < surface.face_count
    assert surface.is_closed_manifold()
    assert np.all((surface.colors >= 0) & (surface.colors <= 1))
    # every corner of a cut face lies on a plane, within the snap of the original mesh's longest edge
    original = wb.tetrahedralize(wb.scenes.tumor(), cellsize=0.2)
    p = original.nodes[original.tets].astype(np.float64)
    longest = max(np.linalg.norm(p[:, i] - p[:, j], axis=1).max() for i in range(4) for j in range(i))
    corners = surface.vertices[surface.faces[surface.is_cut]].reshape(-1, 3).astype(np.float64)
    near = np.min([np.abs((corners - o) @ n) for o, n in _planes()], axis=0)
    assert np.all(near <= SNAP * longest + 1e-5)
    stage = Usd.Stage.Open(str(out / "cut.usda"))
    faces_piece = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Cut/Surface")).GetPrimvar("piece")
    assert faces_piece.GetInterpolation() == UsdGeom.Tokens.uniform and len(faces_piece.Get()) == surface.face_count


def test_prints_one_line_per_cut(cut_run):
    _, text = cut_run
    lines = [line for line in text.splitlines() if line.lstrip().startswith("cut ")]
    assert len(lines) == len(PLANES)
    counts = [int(re.search(r"(\d+) components", line).group(1)) for line in lines]
    assert counts[0] >= 2 and counts == sorted(counts)  # each cut keeps the pieces of the last apart
    for line in lines:
        assert re.search(r"tets split: .*[ABXY] \d+", line) and re.search(r"\d+ tets added", line)
        for stage in wb.cut.STAGES:
            assert re.search(rf"{stage} \d+\.\d", line)


def test_picture_is_written_and_not_blank(cut_run):
    import matplotlib.image

    out, _ = cut_run
    assert (out / "cut.png").read_bytes()[:4] == b"\x89PNG"
    image = matplotlib.image.imread(str(out / "cut.png"))[..., :3]
    drawn = np.any(image < 0.9, axis=2)
    assert drawn.mean() > 0.05  # the pieces cover a good part of the frame
    assert len(np.unique((image[drawn] * 32).astype(int), axis=0)) > 20  # shaded, not one flat colour


@pytest.mark.parametrize(
    "option, value, error, message",
    [
        ("--plane", "0,0,0,0,0,0", wb.CutError, "normal .* must not be zero"),
        ("--plane", "0,0,nan,0,0,1", wb.CutError, "0,0,nan,0,0,1: every number must be finite"),
        ("--cellsize", "0", wb.WarpblobError, "--cellsize must be a positive number, got 0"),
        ("--cellsize", "50", wb.WarpblobError, "--cellsize 50.0 gives no tets"),
        ("--snap", "0.5", wb.CutError, r"--snap must be in \[0, 0.5\), got 0.5"),
        ("--out", "cut.txt", wb.WarpblobError, "--out must be a .usda"),
    ],
)
def test_errors_name_the_value(tmp_path, option, value, error, message):
    options = {"--plane": "0,0,0,0,0,1", "--cellsize": "0.3", "--snap": "0.2", "--out": str(tmp_path / "c.usda")}
    options[option] = value if option != "--out" else str(tmp_path / value)
    argv = ["cut", "tumor"] + [x for item in options.items() for x in item]
    with pytest.raises(error, match=message):
        _run(argv)
    assert not (tmp_path / "c.usda").exists()


def test_main_reports_errors_and_bad_planes(tmp_path, capsys):
    assert main(["cut", "tumor", "--cellsize", "0.3", "--plane", "0,0,0,0,0,0", "--out", str(tmp_path / "c.usda")]) == 1
    assert "must not be zero" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: five numbers
        main(["cut", "tumor", "--cellsize", "0.3", "--plane", "0,0,0,0,1", "--out", str(tmp_path / "c.usda")])
    assert "six numbers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "cut" in capsys.readouterr().out
