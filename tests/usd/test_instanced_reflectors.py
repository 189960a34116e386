"""Reflectors inside instances: authoring on an instance proxy (refused in one line, or
on the prototype with --on-prototype), inspect/validate listing them per instance, and
the selection layer writing and reading their data back (Sdf and composed)."""

from __future__ import annotations

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdGeom, Vt
from typer.testing import CliRunner

import phrt_usd
from phrt_usd.cli import app
from phrt_usd.errors import PhrtError
from phrt_usd.model.frame import FrameStats, ReflectorMetrics
from phrt_usd.run.selection_layer import (
    INSTANCED_PATHS,
    read_selection,
    read_selection_record,
    write_selection_layer,
)
from phrt_usd.usd.authoring import author_reflectors
from phrt_usd.usd.inspection import inspect_stage
from phrt_usd.usd.validation import validate_stage

runner = CliRunner()

TREE = """#usda 1.0
(
    defaultPrim = "Tree"
)
def Xform "Tree"
{
    def Mesh "Leaves"
    {
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)]
        uniform token subdivisionScheme = "none"
    }
}
"""


def _instance(name: str, x: float, asset: str = "tree.usda") -> str:
    return f"""
    def Xform "{name}" (
        instanceable = true
        prepend references = @./{asset}@
    )
    {{
        double3 xformOp:translate = ({x}, 0, 0)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}"""


def _scene(tmp_path, body: str) -> str:
    (tmp_path / "tree.usda").write_text(TREE)
    text = f"""#usda 1.0
(
    defaultPrim = "World"
    upAxis = "Y"
    metersPerUnit = 1
    startTimeCode = 1
    endTimeCode = 1
)
def Xform "World"
{{{body}
    def Camera "Cam"
    {{
        double3 xformOp:translate = (0, 0, 5)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }}
    def DistantLight "Sun"
    {{
        float inputs:intensity = 1
    }}
}}
"""
    path = tmp_path / "scene.usda"
    path.write_text(text)
    return str(path)


@pytest.fixture
def two_trees(tmp_path):
    """Two instances of one tree, its leaves a 1 x 1 quad facing the camera at x = -1, 1."""
    return _scene(tmp_path, _instance("Tree_1", -1.0) + _instance("Tree_2", 1.0))


PROXIES = ["/World/Tree_1/Leaves", "/World/Tree_2/Leaves"]


def test_author_on_an_instance_proxy_is_one_line(two_trees, tmp_path):
    result = runner.invoke(app, ["author", two_trees, PROXIES[0], "--priority", "2"])
    assert result.exit_code == 1, result.output  # a PhrtError: the CLI's "problem" code
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.output
    assert "instance proxy" in lines[0] and "--on-prototype" in lines[0]
    assert "/World/Tree_1" in lines[0] and "tree.usda@/Tree" in lines[0]
    assert not (tmp_path / "scene.phrt.usda").exists()  # nothing written


@pytest.mark.slow
def test_on_prototype_reaches_every_instance_and_keeps_instancing(two_trees, tmp_path):
    result = runner.invoke(
        app, ["author", two_trees, PROXIES[0], "--priority", "2", "--on-prototype"]
    )
    assert result.exit_code == 0, result.output
    stage = Usd.Stage.Open(str(tmp_path / "scene.phrt.usda"))
    for path in PROXIES:
        prim = stage.GetPrimAtPath(path)
        assert prim.IsInstanceProxy()  # still instanced
        assert prim.HasAPI("PhrtReflectorAPI")
        assert prim.GetAttribute("phrt:priority").Get() == 2.0
    assert len(stage.GetPrototypes()) == 1  # both instances still share one prototype
    assert not stage.GetPrimAtPath("/PhrtPrototypes").IsDefined() or stage.GetPrimAtPath(
        "/PhrtPrototypes"
    ).IsAbstract()  # the class is never drawn
    # The referenced asset is untouched.
    assert "Phrt" not in (tmp_path / "tree.usda").read_text()

    summary = inspect_stage(stage)
    assert [r["path"] for r in summary["reflectors"]] == PROXIES
    assert summary["instanced_reflectors"] == 2
    assert [r["instance"] for r in summary["reflectors"]] == ["/World/Tree_1", "/World/Tree_2"]
    prototypes = {r["prototype"] for r in summary["reflectors"]}
    assert len(prototypes) == 1 and prototypes.pop().endswith("/Leaves")
    report = validate_stage(stage)
    assert report.ok, [i.line() for i in report.issues]
    assert report.instanced_reflectors == PROXIES
    text = runner.invoke(app, ["validate", str(tmp_path / "scene.phrt.usda")]).output
    assert "2 reflector(s), 2 inside instances" in text

    # The render reads both instances as reflectors; hybrid with `all` traces both.
    out = tmp_path / "out"
    render = phrt_usd.render(
        tmp_path / "scene.phrt.usda", out, frames="1", mode="hybrid", heuristic="all",
        resolution=(64, 48),
    )  # fmt: skip
    frame = render.frames[0]
    assert sorted(frame.visible) == PROXIES and sorted(frame.selected) == PROXIES
    # Round trip through the selection layer file ...
    _, reflectors, selected, visible = read_selection(render.selection_layer)
    assert reflectors == PROXIES and selected.all() and visible.all()
    # ... and through the composed stage, the layer as a sublayer: on the instance roots.
    composed = Usd.Stage.Open(str(tmp_path / "scene.phrt.usda"))
    composed.GetRootLayer().subLayerPaths.append(str(render.selection_layer))
    for path in PROXIES:
        root = composed.GetPrimAtPath(path.rsplit("/", 1)[0])
        names = list(root.GetAttribute(INSTANCED_PATHS).Get())
        values = root.GetAttribute("phrt:instanced:selected").Get(1.0)
        assert names == [path] and list(values) == [True]


def test_in_place_on_prototype_twice_reuses_the_class(two_trees):
    for k in (2.0, 3.0):
        author_reflectors(two_trees, [PROXIES[1]], k, in_place=True, on_prototype=True)
    stage = Usd.Stage.Open(two_trees)
    assert [c.GetName() for c in stage.GetPrimAtPath("/PhrtPrototypes").GetAllChildren()] == [
        "Tree_1"
    ]
    assert [stage.GetPrimAtPath(p).GetAttribute("phrt:priority").Get() for p in PROXIES] == [
        3.0,
        3.0,
    ]


def test_nested_instancing_is_refused(tmp_path):
    (tmp_path / "tree.usda").write_text(TREE)
    (tmp_path / "grove.usda").write_text(
        '#usda 1.0\n(\n    defaultPrim = "Grove"\n)\ndef Xform "Grove"\n{'
        + _instance("Tree_1", 0.0)
        + "\n}\n"
    )
    stage = _scene(tmp_path, _instance("Grove_1", 0.0, "grove.usda"))
    with pytest.raises(PhrtError, match="nested instancing"):
        author_reflectors(stage, ["/World/Grove_1/Tree_1/Leaves"], 1.0, on_prototype=True)


def _frame(t: float, selected: list[str], visible: list[str]) -> FrameStats:
    metrics = {
        p: ReflectorMetrics(V=0.5, C=0.25, R=1.0, Q=1.0, S=False, selected=p in selected,
                            visible=True)
        for p in visible
    }  # fmt: skip
    return FrameStats(
        time=t, phase_ms={}, frame_ms=1.0, trace_ms=0.5, predicted_trace_ms=0.5, rays=10,
        visible=list(visible), selected=list(selected), metrics=metrics, passes=["gbuffer"],
    )  # fmt: skip


def test_selection_layer_round_trips_instanced_reflectors(tmp_path):
    """A plain reflector, an instance proxy and a PointInstancer element (no prim path at
    all): every one reads back, whole or merged from two halves."""
    plain, proxy, point = "/World/Mirror", "/World/Tree_1/Leaves", "/World/Trees.instance[3]/L"
    reflectors = [plain, proxy, point]
    roots = {proxy: "/World/Tree_1"}  # the point instance's host is found from its path
    rng = np.random.default_rng(7)
    frames = []
    for t in range(1, 9):
        visible = [p for p in reflectors if rng.random() < 0.7]
        frames.append(_frame(float(t), [p for p in visible if rng.random() < 0.5], visible))
    run = {"mode": "hybrid", "heuristic": "heu1"}
    whole = write_selection_layer(
        tmp_path / "whole.usda", None, reflectors, frames, run, 24.0, instance_roots=roots
    )
    merged = tmp_path / "merged.usda"
    write_selection_layer(merged, None, reflectors, frames[4:], run, 24.0, instance_roots=roots)
    write_selection_layer(merged, None, reflectors, frames[:4], run, 24.0, instance_roots=roots)
    for layer_path in (whole, merged):
        record = read_selection_record(layer_path)
        assert record.reflectors == sorted(reflectors)
        np.testing.assert_array_equal(record.times, np.arange(1, 9))
        for column, path in enumerate(record.reflectors):
            assert record.selected[:, column].tolist() == [path in f.selected for f in frames]
            assert record.visible[:, column].tolist() == [path in f.visible for f in frames]
    layer = Sdf.Layer.FindOrOpen(str(whole))
    # No opinion below an instance root and no invalid path: the hosts carry them.
    assert layer.GetPrimAtPath("/World/Tree_1/Leaves") is None
    assert list(layer.GetAttributeAtPath("/World/Trees." + INSTANCED_PATHS).default) == [point]
    # Typed arrays (a Python list would be stored as an unregistered VtValue vector).
    assert isinstance(layer.QueryTimeSample("/World/Tree_1.phrt:instanced:selected", 1.0),
                      Vt.BoolArray)  # fmt: skip
    assert isinstance(layer.QueryTimeSample("/World/Tree_1.phrt:instanced:V", 1.0), Vt.FloatArray)
    # A figure of a frame where the element was no candidate is NaN, never interpolated.
    v = layer.QueryTimeSample("/World/Tree_1.phrt:instanced:V", 1.0)
    assert (proxy in frames[0].visible) == bool(np.isfinite(v[0]))


POINT_INSTANCER = """#usda 1.0
(
    upAxis = "Y"
    metersPerUnit = 1
    startTimeCode = 1
    endTimeCode = 1
)
def Xform "World"
{
    def PointInstancer "Trees"
    {
        point3f[] positions = [(-1, 0, 0), (1, 0, 0)]
        int[] protoIndices = [0, 0]
        rel prototypes = </World/Trees/Protos/Leaf>
        def Scope "Protos"
        {
            def Mesh "Leaf" (
                prepend apiSchemas = ["PhrtReflectorAPI"]
            )
            {
                float phrt:priority = 1
                int[] faceVertexCounts = [4]
                int[] faceVertexIndices = [0, 1, 2, 3]
                point3f[] points = [(-0.5, -0.5, 0), (0.5, -0.5, 0), (0.5, 0.5, 0), (-0.5, 0.5, 0)]
                uniform token subdivisionScheme = "none"
            }
        }
    }
    def Camera "Cam"
    {
        double3 xformOp:translate = (0, 0, 5)
        uniform token[] xformOpOrder = ["xformOp:translate"]
    }
    def DistantLight "Sun"
    {
        float inputs:intensity = 1
    }
}
"""


def test_point_instancer_reflectors_render_into_the_selection_layer(tmp_path):
    """PointInstancer elements (``/World/Trees.instance[i]``, no prim path) used to stop
    the selection layer writer; they go on the instancer and read back."""
    stage = tmp_path / "pi.usda"
    stage.write_text(POINT_INSTANCER)
    render = phrt_usd.render(stage, tmp_path / "out", frames="1", mode="hybrid",
                             heuristic="all", resolution=(64, 48))  # fmt: skip
    elements = ["/World/Trees.instance[0]", "/World/Trees.instance[1]"]
    assert sorted(render.frames[0].selected) == elements
    _, reflectors, selected, _ = read_selection(render.selection_layer)
    assert reflectors == elements and selected.all()
    composed = Usd.Stage.Open(str(stage))
    composed.GetRootLayer().subLayerPaths.append(str(render.selection_layer))
    trees = composed.GetPrimAtPath("/World/Trees")
    assert list(trees.GetAttribute(INSTANCED_PATHS).Get()) == elements
    assert list(trees.GetAttribute("phrt:instanced:selected").Get(1.0)) == [True, True]


def test_inspect_counts_the_instances_of_a_point_instancer_reflector(tmp_path):
    """A reflector in a PointInstancer prototype is one prim but as many elements as the
    instances the mask leaves: inspect names the instancer and that count, nested
    instancers multiplying (an outer instancer of 3 instances around this one: 3 x 1)."""
    path = tmp_path / "pi.usda"
    path.write_text(POINT_INSTANCER)
    result = CliRunner().invoke(app, ["inspect", str(path)], env={"COLUMNS": "250"})
    assert result.exit_code == 0 and "(2 instances of /World/Trees)" in result.output
    stage = Usd.Stage.Open(str(path))
    [leaf] = inspect_stage(stage)["reflectors"]
    assert (leaf["point_instancer"], leaf["instances"]) == ("/World/Trees", 2)
    trees = stage.GetPrimAtPath("/World/Trees")
    trees.GetAttribute("invisibleIds").Set(Vt.Int64Array([1]))
    [leaf] = inspect_stage(stage)["reflectors"]
    assert leaf["instances"] == 1
    outer = UsdGeom.PointInstancer.Define(stage, "/Forest")
    outer.CreatePositionsAttr([(0, 0, 0), (5, 0, 0), (10, 0, 0)])
    outer.CreateProtoIndicesAttr([0, 0, 0])
    outer.CreatePrototypesRel().SetTargets(["/World"])
    [leaf] = inspect_stage(stage)["reflectors"]
    assert (leaf["point_instancer"], leaf["instances"]) == ("/World/Trees", 3)
