"""The ``warpblob`` command: subcommands, outputs and error paths (run as subprocesses)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import warpblob as wb


def run_cli(*args, cwd=None):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run(
        [sys.executable, "-m", "warpblob.cli", *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=600
    )


def test_help_lists_subcommands():
    r = run_cli("--help")
    assert r.returncode == 0
    for name in ("demo", "info", "field"):
        assert name in r.stdout


def test_info_matches_linearize():
    r = run_cli("info", "tumor", "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    lm = wb.linearize(wb.scenes.tumor())
    assert (info["primitives"], info["operators"], info["depth"]) == (lm.primitive_count, lm.operator_count, lm.depth)
    assert info["nbytes"] == lm.nbytes


def test_field_writes_values(tmp_path):
    pts = np.random.default_rng(0).uniform(-2, 2, (500, 3)).astype(np.float32)
    np.save(tmp_path / "pts.npy", pts)
    out = tmp_path / "f.npy"
    r = run_cli("field", "peanut", "--points", str(tmp_path / "pts.npy"), "--out", str(out))
    assert r.returncode == 0, r.stderr
    np.testing.assert_array_equal(np.load(out), wb.field(wb.scenes.peanut(), pts))
    assert not any(p.name.endswith(".tmp.npy") for p in tmp_path.iterdir())


@pytest.mark.parametrize(
    "args, words",
    [
        (("info", "no_such_scene"), "unknown scene 'no_such_scene'"),
        (("field", "tumor", "--points", "missing.npy"), "missing.npy"),
        (("--device", "cuda:7", "info", "tumor"), None),
        (("demo", "--resolution", "2"), "--resolution"),
    ],
)
def test_errors_are_one_line(tmp_path, args, words):
    r = run_cli(*args, cwd=tmp_path)
    if words is None:  # info does not touch the device: it must still succeed
        assert r.returncode == 0, r.stderr
        return
    assert r.returncode != 0
    assert "Traceback" not in r.stderr
    assert words in r.stderr
    assert len([line for line in r.stderr.splitlines() if line.startswith("warpblob")]) == 1


def test_field_rejects_bad_points(tmp_path):
    np.save(tmp_path / "bad.npy", np.zeros((4, 2)))
    r = run_cli("field", "tumor", "--points", str(tmp_path / "bad.npy"))
    assert r.returncode == 1
    assert "(4, 2)" in r.stderr and "Traceback" not in r.stderr


def test_field_bad_device(tmp_path):
    np.save(tmp_path / "p.npy", np.zeros((4, 3)))
    r = run_cli("--device", "cuda:7", "field", "tumor", "--points", str(tmp_path / "p.npy"))
    assert r.returncode == 1
    assert "cuda:7" in r.stderr and "Traceback" not in r.stderr


def test_demo_writes_pictures_and_summary(tmp_path):
    out = tmp_path / "out"
    r = run_cli("demo", "--out", str(out), "--scene", "peanut", "--resolution", "64")
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["peanut"]["primitives"] == 2
    assert 0.0 < summary["peanut"]["inside_fraction"] < 1.0
    png = (out / "peanut_slices.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    assert not any(".tmp" in p.name for p in out.iterdir())


def test_info_and_field_read_usd_scenes(tmp_path):
    scene = os.path.join(os.path.dirname(__file__), "..", "usd_scenes", "tumor.usda")
    r = run_cli("info", scene, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["primitives"] == 10
    pts = np.random.default_rng(1).uniform(-2, 2, (300, 3)).astype(np.float32)
    np.save(tmp_path / "p.npy", pts)
    r = run_cli("field", scene, "--points", str(tmp_path / "p.npy"), "--out", str(tmp_path / "f.npy"))
    assert r.returncode == 0, r.stderr
    np.testing.assert_allclose(np.load(tmp_path / "f.npy"), wb.field(wb.scenes.tumor(), pts), atol=1e-6)


@pytest.mark.parametrize("content, words", [(None, "does not exist"), ("#usda 1.0\n(\n", "scene.usda")])
def test_bad_usd_scene_is_one_line(tmp_path, content, words):
    path = tmp_path / "scene.usda"
    if content is not None:
        path.write_text(content)
    r = run_cli("info", str(path))
    assert r.returncode == 1
    assert "Traceback" not in r.stderr and words in r.stderr
