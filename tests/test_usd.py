"""USD scenes (docs/usd_format.md): round trips, reference files, hand-written and malformed scenes."""

import os
import pathlib
import re
import runpy
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdValidation

import warpblob as wb
import warpblob.usd as wbusd
from warpblob.io import usd as usd_io

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ROOT / "usd_scenes"
DOCS = ROOT / "docs" / "usd_format.md"
MAKE_SCENES = runpy.run_path(str(SCENES / "make_scenes.py"))


# ---------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------


def assert_same_structure(a, b, where="root"):
    """Same node types, parameters, derived frames, colours and transforms, operand by operand."""
    stack = [(a, b, where)]
    while stack:
        x, y, path = stack.pop()
        assert type(x) is type(y), f"{path}: {type(x).__name__} != {type(y).__name__}"
        assert len(x.children) == len(y.children), f"{path}: operand count"
        if isinstance(x, wb.Transform):
            np.testing.assert_allclose(x.matrix, y.matrix, rtol=0, atol=1e-12, err_msg=path)
        for name, vx in vars(x).items():
            if name.startswith("_"):
                continue
            vy = getattr(y, name)
            if isinstance(vx, wb.Sketch):
                vx, vy = vx.points, vy.points
            # colours are float32 in USD; unit vectors renormalized on load move by an ulp
            atol = 1e-6 if name == "color" else 1e-12
            np.testing.assert_allclose(vx, vy, rtol=0, atol=atol, err_msg=f"{path}.{name}")
        stack.extend((cx, cy, f"{path}/{i}") for i, (cx, cy) in enumerate(zip(x.children, y.children)))


def random_points(model, n=2000, seed=0):
    lower, upper = model.bounds()
    return np.random.default_rng(seed).uniform(lower, upper, (n, 3))


def assert_same_field(a, b, n=2000):
    p = random_points(a, n)
    fa, fb = wb.field(a, p), wb.field(b, p)
    assert np.count_nonzero(fa) > 0
    np.testing.assert_allclose(fa, fb, rtol=0, atol=1e-6)


def validation_errors(path):
    """Errors (not warnings) of every registered UsdValidation validator: what `usdchecker` runs."""
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [e.GetErrorAsString() for e in errors if e.GetType() == UsdValidation.ValidationErrorType.Error]


def all_kinds():
    """One model with every primitive, operator and warp kind, and transforms."""
    sq = wb.Sketch([[0.2, -0.3], [0.6, -0.3], [0.6, 0.3], [0.2, 0.3]])
    p = [
        wb.Point((0, 0, 0), 0.8, color=(1, 0, 0)),
        wb.Segment((0, 0, 0), (1, 0.2, 0), 0.5),
        wb.Disc((0, 1, 0), (0, 1, 1), 0.4, 0.3),
        wb.Ring((1, 1, 0), (1, 0, 0), 0.5, 0.3, color=(0, 1, 0)),
        wb.Cylinder((0, 0, 1), (0, 0, 2), 0.3, 0.4),
        wb.Cone((1, 0, 1), (1, 0, 2), 0.4, 0.0, 0.4),
        wb.Triangle((0, 0, 0), (1, 0, 0), (0, 1, 0.5), 0.3),
        wb.Polygon([[0, 0, 0], [1, 0, 0], [1.2, 1, 0], [0.5, 0.4, 0], [0, 1, 0]], 0.3),
        wb.Box((0, 0, -1), (0.5, 0.3, 0.0), 0.3),
        wb.Inflate(sq, thickness=0.15, radius=0.3),
        wb.Revolve(sq, axis=(1, 1, 0), center=(0.5, 0, 0), radius=0.3),
        wb.Sweep(sq, [[0, 0, 0], [0, 0, 1], [1, 0, 1.5]], radius=0.25),
    ]
    a = wb.SmoothBlend(p[0], p[1], p[2], k=3.0)
    b = wb.Twist(wb.Union(p[3], p[4]), (0, 0, 1), 0.4)
    c = wb.Taper(wb.Intersection(p[5], p[6] + p[7]), (0, 0, 1), 0.1)
    d = wb.Bend(wb.Blend(p[8], p[9]), (1, 0, 0), (0, 0, 1), -0.3)
    e = (p[10] | p[11]).scale((1, 2, 0.5)).translate((0, 0, 3))
    return wb.Difference(wb.Blend(a, b.rotate((1, 0, 0), 0.3), c, d, e), wb.Point((0, 0, 0), 0.2))


@pytest.fixture(scope="module")
def models():
    return {name: fn() for name, fn in wb.scenes.ALL.items()}


# ---------------------------------------------------------------------------
# round trips and the reference scenes
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(wb.scenes.ALL))
def test_round_trip_reference_model(models, tmp_path, name):
    model = models[name]
    loaded = wbusd.load_model(wbusd.save_model(model, tmp_path / f"{name}.usda"))
    assert_same_structure(model, loaded)
    assert (loaded.primitive_count(), loaded.operator_count(), loaded.depth()) == (
        model.primitive_count(),
        model.operator_count(),
        model.depth(),
    )
    assert_same_field(model, loaded)


@pytest.mark.parametrize("suffix", [".usda", ".usdc", ".usd"])
def test_round_trip_every_kind(tmp_path, suffix):
    model = all_kinds()
    loaded = wbusd.load_model(wbusd.save_model(model, tmp_path / f"all{suffix}"))
    assert_same_structure(model, loaded)
    assert_same_field(model, loaded, n=4000)


def test_round_trip_keeps_identity_transforms_and_lone_primitives(tmp_path):
    lone = wb.Point((1, 2, 3), 0.5, color=(0.1, 0.2, 0.3))
    loaded = wbusd.load_model(wbusd.save_model(lone, tmp_path / "lone.usda"))
    assert_same_structure(lone, loaded)
    wrapped = wb.Union(lone.translate((0, 0, 0)), wb.Segment((0, 0, 0), (1, 0, 0), 0.4))
    loaded = wbusd.load_model(wbusd.save_model(wrapped, tmp_path / "id.usda"))
    assert_same_structure(wrapped, loaded)
    assert isinstance(loaded.children[0], wb.Transform)


def test_reference_scene_files_are_complete_and_current(models):
    files = MAKE_SCENES["scene_files"]()
    assert sorted(p.name for p in SCENES.glob("*.usda")) == sorted(p.name for p in files.values())
    assert files["three_slabs"].name == "3slabs.usda"
    for name, path in files.items():
        loaded = wbusd.load_model(path)
        assert_same_structure(models[name], loaded, where=path.name)
        assert_same_field(models[name], loaded, n=500)
        assert path.stat().st_size < 4e6, f"{path.name} is {path.stat().st_size / 1e6:.1f} MB"


def test_make_scenes_is_deterministic(tmp_path):
    written = MAKE_SCENES["main"](tmp_path)
    assert len(written) == len(wb.scenes.ALL)
    for path in written:
        assert path.read_bytes() == (SCENES / path.name).read_bytes(), f"usd_scenes/{path.name} is out of date"


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.usda")), ids=lambda p: p.name)
def test_reference_scene_passes_usd_validation(path):
    assert validation_errors(path) == []


# ---------------------------------------------------------------------------
# what the file looks like to USD and DCC tools
# ---------------------------------------------------------------------------


def test_stage_metadata_and_root(tmp_path):
    path = wbusd.save_model(wb.scenes.peanut(), tmp_path / "p.usda", meters_per_unit=1.0, doc="a peanut")
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/Model"
    assert stage.GetRootLayer().documentation == "a peanut"
    root = stage.GetDefaultPrim()
    assert root.GetTypeName() == "Xform"
    assert root.GetAttribute("warpblob:version").Get() == wbusd.FORMAT_VERSION
    assert root.GetAttribute("warpblob:kind").Get() == "blend"
    stage = Usd.Stage.Open(str(wbusd.save_model(wb.scenes.peanut(), tmp_path / "q.usda", prim_path="/Nut")))
    assert UsdGeom.GetStageMetersPerUnit(stage) == wbusd.METERS_PER_UNIT == 0.01
    assert stage.GetDefaultPrim().GetPath() == "/Nut"


def test_every_primitive_has_a_coloured_guide(tmp_path):
    model = all_kinds()
    stage = Usd.Stage.Open(str(wbusd.save_model(model, tmp_path / "all.usda")))
    prims = [p for p in stage.Traverse() if p.GetAttribute("warpblob:kind").Get() in usd_io._KINDS]
    primitives = [p for p in prims if usd_io._KINDS[p.GetAttribute("warpblob:kind").Get()].is_primitive]
    assert len(primitives) == model.primitive_count()
    for prim in primitives:
        guide = prim.GetChild("guide")
        assert guide.IsA(UsdGeom.Gprim), prim.GetPath()
        assert UsdGeom.Imageable(guide).GetPurposeAttr().Get() == UsdGeom.Tokens.guide
        inherited = UsdGeom.PrimvarsAPI(guide).FindPrimvarWithInheritance("displayColor")
        assert inherited.HasAuthoredValue() and len(inherited.Get()) == 1, prim.GetPath()
        assert prim.GetAttribute("primvars:displayColor").HasAuthoredValue()
    kinds = {p.GetChild("guide").GetTypeName() for p in primitives}
    assert kinds == {"Sphere", "BasisCurves", "Mesh", "Cube"}
    assert validation_errors(tmp_path / "all.usda") == []


def test_usd_transforms_place_guides_where_warpblob_puts_primitives(tmp_path):
    m = wb.Point((1, 0, 0), 0.5).rotate((0, 0, 1), np.pi / 2).scale(2).translate((0, 0, 5))
    model = wb.Union(m, wb.Point((0, 0, 0), 0.5).translate((3, 0, 0)))
    stage = Usd.Stage.Open(str(wbusd.save_model(model, tmp_path / "t.usda")))
    centres = []
    for prim in stage.Traverse():
        if prim.GetName() == "guide":
            world = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
            centres.append(np.array(world.Transform(Gf.Vec3d(0, 0, 0))))
    expected = [m.matrix @ [1, 0, 0, 1], [3, 0, 0, 1]]
    np.testing.assert_allclose(centres, np.array(expected)[:, :3], atol=1e-12)
    ops = {p.GetName(): UsdGeom.Xformable(p).GetXformOpOrderAttr().Get() for p in stage.Traverse()}
    assert list(ops["point_1"]) == ["xformOp:translate"]  # pure translations stay readable
    assert list(ops["point_0"]) == ["xformOp:transform"]


def test_repeated_subtrees_are_written_once_and_referenced(models):
    stage = Usd.Stage.Open(str(SCENES / "towers.usda"))
    prototypes = stage.GetPrimAtPath("/Model/prototypes")
    assert prototypes.IsAbstract()
    assert len(prototypes.GetFilteredChildren(Usd.PrimAllPrimsPredicate)) == 4
    references = [p for p in stage.Traverse() if p.HasAuthoredReferences()]
    assert len(references) == 64
    tower = references[0]
    assert tower.GetAttribute("warpblob:kind").Get() == "union"  # composed from the prototype
    assert tower.GetAttribute("xformOpOrder").Get() == ["xformOp:translate"]


def test_importing_warpblob_does_not_import_pxr():
    code = "import sys, warpblob; assert 'pxr' not in sys.modules; import warpblob.usd; assert 'pxr' in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


# ---------------------------------------------------------------------------
# scenes written by hand
# ---------------------------------------------------------------------------


def test_documented_example_loads_as_documented(tmp_path):
    text = DOCS.read_text()
    usda = re.search(r"```usda\n(.*?)```", text, re.S).group(1)
    code = re.findall(r"```python\n(.*?)```", text, re.S)[-1]
    (tmp_path / "doc.usda").write_text(usda)
    namespace = {}
    exec(code, namespace)
    loaded = wbusd.load_model(tmp_path / "doc.usda")
    assert_same_structure(namespace["model"], loaded)
    assert_same_field(namespace["model"], loaded, n=4000)


def test_docs_name_every_kind_and_attribute():
    text = DOCS.read_text()
    for kind, spec in usd_io._KINDS.items():
        assert f"`{kind}`" in text, kind
        for p in spec.params:
            assert f"`{p.attr}`" in text, p.attr


HAND_WRITTEN = """#usda 1.0
(
    defaultPrim = "Model"
    metersPerUnit = 0.01
    upAxis = "Z"
)

def Xform "Model"
{
    uniform token warpblob:kind = "union"
    color3f[] primvars:displayColor = [(0.5, 0.5, 0.5)]

    def Xform "bent"
    {
        uniform int warpblob:order = 10
        uniform token warpblob:kind = "bend"
        vector3f warpblob:up = (0, 0, 1)
        double warpblob:rate = 0.2
        double3 xformOp:translate = (0, 0, 1)
        uniform token[] xformOpOrder = ["xformOp:translate"]

        def Xform "rod" (
            prepend inherits = </Templates/rod>
        )
        {
            uniform int warpblob:order = 0
        }
    }

    def Xform "vase"
    {
        uniform int warpblob:order = 2
        uniform token warpblob:kind = "revolve"
        double2[] warpblob:sketch = [(0, 0), (0.5, 0), (0.8, 1), (0.3, 2), (0, 2)]
        float3 xformOp:scale = (1, 1, 2)
        float xformOp:rotateX = 90
        uniform token[] xformOpOrder = ["xformOp:scale", "xformOp:rotateX"]

        def Mesh "my_mesh"
        {
        }
    }

    def Xform "tapered" (
        instanceable = true
        references = </Templates/tapered_tube>
    )
    {
        uniform int warpblob:order = -1
    }

    def Xform "switched_off" (
        active = false
    )
    {
        uniform int warpblob:order = 3
        uniform token warpblob:kind = "point"
    }
}

class "Templates"
{
    def Xform "rod"
    {
        uniform token warpblob:kind = "segment"
        point3d warpblob:a = (-2, 0, 0)
        double3 warpblob:b = (2, 0, 0)
        float warpblob:radius = 0.5
        color3f[] primvars:displayColor = [(1, 0, 0), (0, 1, 0)]
    }

    def Xform "tapered_tube"
    {
        uniform token warpblob:kind = "taper"
        double3 warpblob:axis = (0, 0, 1)
        double warpblob:slope = 0.25

        def Xform "tube"
        {
            uniform int warpblob:order = 0
            uniform token warpblob:kind = "sweep"
            double2[] warpblob:sketch = [(0.3, 0.3), (-0.3, 0.3), (-0.3, -0.3), (0.3, -0.3)]
            double3[] warpblob:path = [(2, 0, 0), (2, 0, 1), (2.5, 0, 2)]
        }
    }
}
"""


def test_hand_written_scene_with_composition_and_defaults(tmp_path):
    """Role and float types, defaults, inherits, an instanced reference, inactive and foreign prims, order gaps."""
    (tmp_path / "hand.usda").write_text(HAND_WRITTEN)
    loaded = wbusd.load_model(tmp_path / "hand.usda")
    grey = (0.5, 0.5, 0.5)
    square = wb.Sketch([(0.3, 0.3), (-0.3, 0.3), (-0.3, -0.3), (0.3, -0.3)])
    tapered = wb.Taper(wb.Sweep(square, [(2, 0, 0), (2, 0, 1), (2.5, 0, 2)], color=grey), (0, 0, 1), 0.25)
    rod = wb.Segment((-2, 0, 0), (2, 0, 0), 0.5, color=(1, 0, 0))
    bent = wb.Bend(rod, up=(0, 0, 1), rate=0.2).translate((0, 0, 1))
    profile = wb.Sketch([(0, 0), (0.5, 0), (0.8, 1), (0.3, 2), (0, 2)])
    vase = wb.Revolve(profile, color=grey).rotate((1, 0, 0), np.pi / 2).scale((1, 1, 2))
    expected = wb.Union(tapered, vase, bent)  # orders -1, 2, 10
    assert_same_structure(expected, loaded)
    assert_same_field(expected, loaded, n=4000)
    part = wbusd.load_model(tmp_path / "hand.usda", prim_path="/Model/tapered")
    assert_same_structure(tapered, part)


# ---------------------------------------------------------------------------
# malformed scenes
# ---------------------------------------------------------------------------

VALID = """#usda 1.0
(
    defaultPrim = "Model"
)

def Xform "Model"
{
    uniform token warpblob:kind = "difference"

    def Xform "body"
    {
        uniform int warpblob:order = 0
        uniform token warpblob:kind = "twist"
        double3 warpblob:axis = (0, 0, 1)
        double warpblob:rate = 0.5

        def Xform "ball"
        {
            uniform int warpblob:order = 0
            uniform token warpblob:kind = "point"
            double3 warpblob:center = (0, 0, 0)
            double warpblob:radius = 1
        }
    }

    def Xform "hole"
    {
        uniform int warpblob:order = 1
        uniform token warpblob:kind = "point"
        double3 warpblob:center = (0.5, 0, 0)
        double warpblob:radius = 0.5
    }
}
"""

EXTRA_CHILD = """
        def Xform "extra"
        {{
            uniform int warpblob:order = {order}
            uniform token warpblob:kind = "point"
            double3 warpblob:center = (0, 0, 1)
            double warpblob:radius = 1
        }}
"""

#: name -> (edit of VALID: (old, new), prim path and attribute the message must name)
MALFORMED = {
    "unknown kind": (('kind = "twist"', 'kind = "swirl"'), "</Model/body>", "warpblob:kind"),
    "kind not a token": (('uniform token warpblob:kind = "twist"', 'string warpblob:kind = "twist"'),
                         "</Model/body>", "warpblob:kind"),
    "missing kind": (('uniform token warpblob:kind = "twist"', ""), "</Model/body>", "warpblob:kind"),
    "missing attribute": (("double warpblob:rate = 0.5", ""), "</Model/body>", "warpblob:rate"),
    "missing radius": (("double warpblob:radius = 0.5", ""), "</Model/hole>", "warpblob:radius"),
    "string radius": (("double warpblob:radius = 0.5", 'string warpblob:radius = "0.5"'),
                      "</Model/hole>", "warpblob:radius"),
    "int radius": (("double warpblob:radius = 0.5", "int warpblob:radius = 1"), "</Model/hole>", "warpblob:radius"),
    "scalar centre": (("double3 warpblob:center = (0.5, 0, 0)", "double warpblob:center = 0.5"),
                      "</Model/hole>", "warpblob:center"),
    "declared without value": (("double warpblob:radius = 0.5", "double warpblob:radius"),
                               "</Model/hole>", "warpblob:radius"),
    "relationship": (("double3 warpblob:center = (0.5, 0, 0)", "rel warpblob:center = </Model>"),
                     "</Model/hole>", "warpblob:center"),
    "misspelt attribute": (("double warpblob:radius = 0.5", "double warpblob:raduis = 0.5"),
                           "</Model/hole>", "warpblob:raduis"),
    "negative radius": (("double warpblob:radius = 0.5", "double warpblob:radius = -0.5"),
                        "</Model/hole>", "warpblob:radius"),
    "zero axis": (("double3 warpblob:axis = (0, 0, 1)", "double3 warpblob:axis = (0, 0, 0)"),
                  "</Model/body>", "warpblob:axis"),
    "bad colour": (("double warpblob:radius = 0.5",
                    "double warpblob:radius = 0.5\n color3f[] primvars:displayColor = [(2, 0, 0)]"),
                   "</Model/hole>", "primvars:displayColor"),
    "missing order": (("uniform int warpblob:order = 1", ""), "</Model/hole>", "warpblob:order"),
    "duplicate order": (("uniform int warpblob:order = 1", "uniform int warpblob:order = 0"),
                        "</Model/", "warpblob:order"),
    "difference of 1": (('def Xform "hole"', 'def Xform "hole" (\n active = false\n )'), "</Model>", None),
    "difference of 3": (("    def Xform \"hole\"", EXTRA_CHILD.format(order=2) + "    def Xform \"hole\""),
                        "</Model>", None),
    "twist of 2": (("        def Xform \"ball\"", EXTRA_CHILD.format(order=1) + "        def Xform \"ball\""),
                   "</Model/body>", None),
    "primitive with an operand": (("double3 warpblob:center = (0.5, 0, 0)",
                                   "double3 warpblob:center = (0.5, 0, 0)\n" + EXTRA_CHILD.format(order=0)),
                                  "</Model/hole>", None),
    "typeless node prim": (('def Xform "hole"', 'def "hole"'), "</Model/hole>", None),
    "singular transform": (("double warpblob:radius = 0.5", "double warpblob:radius = 0.5\n"
                            " float3 xformOp:scale = (1, 0, 1)\n uniform token[] xformOpOrder = [\"xformOp:scale\"]"),
                           "</Model/hole>", "xformOpOrder"),
    "newer version": (('uniform token warpblob:kind = "difference"',
                       'uniform token warpblob:kind = "difference"\n uniform int warpblob:version = 99'),
                      "</Model>", "warpblob:version"),
    "reference cycle": (('def Xform "ball"', 'def Xform "ball" (\n references = </Model>\n )'),
                        "</Model/body/ball>", "cycle"),
    "missing referenced file": (('def Xform "ball"', 'def Xform "ball" (\n references = @nowhere.usda@\n )'),
                                "</Model/body/ball>", "nowhere.usda"),
}


def test_valid_template_loads(tmp_path):
    (tmp_path / "ok.usda").write_text(VALID)
    model = wbusd.load_model(tmp_path / "ok.usda")
    assert isinstance(model, wb.Difference) and isinstance(model.children[0], wb.Twist)


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_scene_raises_scene_error_naming_prim_and_attribute(tmp_path, case):
    (old, new), prim, attr = MALFORMED[case]
    assert old in VALID
    path = tmp_path / "bad.usda"
    path.write_text(VALID.replace(old, new, 1))
    with pytest.raises(wb.SceneError) as info:
        wbusd.load_model(path)
    message = str(info.value)
    assert str(path) in message
    assert prim in message, message
    if attr:
        assert attr in message, message


@pytest.mark.parametrize(
    "content",
    [os.urandom(4096), b"hello, this is not a scene\n", b"#usda 1.0\ndef Xform \"Model\" {\n", b""],
    ids=["random bytes", "text", "truncated usda", "empty"],
)
@pytest.mark.parametrize("suffix", [".usda", ".usd", ".txt"])
def test_file_that_is_not_usd(tmp_path, content, suffix):
    path = tmp_path / f"bad{suffix}"
    path.write_bytes(content)
    with pytest.raises(wb.SceneError, match=re.escape(str(path))):
        wbusd.load_model(path)


def test_missing_prim_path_and_file(tmp_path):
    path = wbusd.save_model(wb.scenes.mug(), tmp_path / "mug.usda")
    with pytest.raises(wb.SceneError, match="</Model/nothing>"):
        wbusd.load_model(path, prim_path="/Model/nothing")
    with pytest.raises(wb.SceneError, match="warpblob:kind"):
        wbusd.load_model(path, prim_path="/Model/cylinder_1/guide")
    with pytest.raises(wb.SceneError, match="absolute"):
        wbusd.load_model(path, prim_path="Model")
    with pytest.raises(wb.SceneError, match=re.escape(str(tmp_path / "absent.usda"))):
        wbusd.load_model(tmp_path / "absent.usda")


def test_stage_without_default_prim(tmp_path):
    path = tmp_path / "nodefault.usda"
    path.write_text(VALID.replace('defaultPrim = "Model"', ""))
    assert isinstance(wbusd.load_model(path), wb.Difference)  # its only root prim
    path.write_text(VALID.replace('defaultPrim = "Model"', "") + '\ndef Xform "Other"\n{\n}\n')
    with pytest.raises(wb.SceneError, match="prim_path"):
        wbusd.load_model(path)


# ---------------------------------------------------------------------------
# atomic writes
# ---------------------------------------------------------------------------


class Alien(wb.Node):
    kind = "alien"

    def _compute_bounds(self):
        return np.zeros(3), np.ones(3)


def test_failed_save_writes_nothing(tmp_path):
    with pytest.raises(wb.ModelError, match="Alien"):
        wbusd.save_model(wb.Union(wb.scenes.peanut(), Alien()), tmp_path / "x.usda")
    with pytest.raises(wb.ModelError, match="not a model"):
        wbusd.save_model("not a model", tmp_path / "x.usda")
    with pytest.raises(wb.SceneError, match="suffix|end in"):
        wbusd.save_model(wb.scenes.peanut(), tmp_path / "x.obj")
    with pytest.raises(wb.SceneError, match="prim_path"):
        wbusd.save_model(wb.scenes.peanut(), tmp_path / "x.usda", prim_path="/A/B")
    with pytest.raises(wb.SceneError, match="does not exist"):
        wbusd.save_model(wb.scenes.peanut(), tmp_path / "missing" / "x.usda")
    assert list(tmp_path.iterdir()) == []


def test_failed_save_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    path = wbusd.save_model(wb.scenes.peanut(), tmp_path / "m.usda")
    before = path.read_bytes()

    def broken_replace(src, dst):
        assert pathlib.Path(src).exists() and pathlib.Path(src).parent == pathlib.Path(dst).parent
        raise OSError("disk full")

    monkeypatch.setattr(usd_io.os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        wbusd.save_model(wb.scenes.tumor(), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["m.usda"]
    monkeypatch.undo()
    wbusd.save_model(wb.scenes.tumor(), path)
    assert [p.name for p in tmp_path.iterdir()] == ["m.usda"]
    assert wbusd.load_model(path).primitive_count() == 10


WRITERS = {
    "save_model": lambda path: wbusd.save_model(wb.scenes.peanut(), path),
    "save_mesh": lambda path: wbusd.save_mesh(wb.polygonize(wb.scenes.peanut(), cellsize=0.3), path),
    "save_tetmesh": lambda path: wbusd.save_tetmesh(wb.TetMesh(np.eye(4, 3, k=-1), [[0, 1, 2, 3]]), path),
}


@pytest.mark.parametrize("writer", list(WRITERS))
def test_writers_check_the_path_first_and_write_atomically(tmp_path, writer, monkeypatch):
    write = WRITERS[writer]
    (tmp_path / "folder.usda").mkdir()
    for bad, words in (
        (tmp_path / "missing" / "x.usda", "does not exist"),
        (tmp_path / "x.obj", "must end in"),
        (tmp_path / "folder.usda", "is a folder"),
    ):
        with pytest.raises(wb.SceneError, match=words) as info:
            write(bad)
        assert str(bad) in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.usda"]
    path = write(tmp_path / "m.usda")
    before = path.read_bytes()

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(usd_io.os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        write(path)
    assert path.read_bytes() == before  # the old file, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.usda", "m.usda"]  # no temporary left


def _mesh_file(tmp_path):
    return wbusd.save_mesh(wb.polygonize(wb.scenes.peanut(), cellsize=0.3), tmp_path / "mesh.usda")


LOADERS = {
    "load_model": (wbusd.load_model, lambda tmp: wbusd.save_model(wb.scenes.peanut(), tmp / "model.usda")),
    "load_mesh": (wbusd.load_mesh, _mesh_file),
    "load_tetmesh": (
        wbusd.load_tetmesh,
        lambda tmp: wbusd.save_tetmesh(wb.TetMesh(np.eye(4, 3, k=-1), [[0, 1, 2, 3]]), tmp / "tets.usda"),
    ),
}


@pytest.mark.parametrize("case", ["missing file", "folder", "not USD", "missing prim"])
@pytest.mark.parametrize("loader", list(LOADERS))
def test_every_loader_raises_scene_error_naming_the_path(tmp_path, loader, case):
    load, make = LOADERS[loader]
    kwargs = {}
    if case == "missing file":
        path = tmp_path / "absent.usda"
    elif case == "folder":
        path = tmp_path / "folder.usda"
        path.mkdir()
    elif case == "not USD":
        path = tmp_path / "text.usda"
        path.write_text("hello, this is not a scene\n")
    else:
        path = make(tmp_path)
        kwargs = {"prim_path": "/Nothing"}
    with pytest.raises(wb.SceneError) as info:
        load(path, **kwargs)
    assert str(path) in str(info.value)
    if case == "missing prim":
        assert "/Nothing" in str(info.value)


def test_load_mesh_round_trip_and_wrong_prim_kind(tmp_path):
    mesh = wb.polygonize(wb.scenes.peanut(), cellsize=0.3)
    path = wbusd.save_mesh(mesh, tmp_path / "mesh.usda")
    back = wbusd.load_mesh(path)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(wbusd.load_mesh(path, prim_path="/Surface").faces, mesh.faces)
    model = wbusd.save_model(wb.scenes.peanut(), tmp_path / "model.usda")
    with pytest.raises(wb.SceneError, match="not a UsdGeom.Mesh"):
        wbusd.load_mesh(model)
