"""The selection round loop (select/rounds.py): written once, run by the renderer and the
replay tool alike, and reading nothing of a policy but what ``SelectionPolicy`` states."""

from __future__ import annotations

import ast
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from repo_paths import REPO, TOOLS

from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.model.frame import Budget, FrameNote, FrameView, SelectionPolicy, TraceRecord
from phrt_usd.model.scene import CameraFrame
from phrt_usd.select.policies import POLICY_NAMES, make_policy
from phrt_usd.select.rounds import Calibration, TracedRound, run_rounds
from phrt_usd.usd.stage import open_stage

if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))
import policy_replay  # noqa: E402

#: Where the round loop may be driven: the package and the tools (tests drive policies
#: directly to test them one call at a time).
SOURCES = sorted([*(REPO / "phrt_usd").rglob("*.py"), *TOOLS.glob("*.py")])
ROUND_LOOP = REPO / "phrt_usd" / "select" / "rounds.py"


def _calls(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call):
            yield node


@pytest.mark.slow
def test_probe_the_round_loop_is_written_once():
    # A policy's rounds are asked for in one place: the renderer and the replay tool both
    # run ``run_rounds``, so a replay selects what a render of the same views does.
    drivers = sorted(
        str(path.relative_to(REPO))
        for path in SOURCES
        for call in _calls(path)
        if isinstance(call.func, ast.Attribute) and call.func.attr == "next_round"
    )
    assert drivers == [str(ROUND_LOOP.relative_to(REPO))]


@pytest.mark.slow
def test_probe_no_policy_attribute_is_read_through_getattr():
    # What the renderer reads of a policy is stated by SelectionPolicy, so nothing needs
    # getattr / hasattr with a default to read a policy.
    found = []
    for path in SOURCES:
        for call in _calls(path):
            if isinstance(call.func, ast.Name) and call.func.id in ("getattr", "hasattr"):
                target = ast.unparse(call.args[0]) if call.args else ""
                if "policy" in target.lower():
                    found.append(f"{path.relative_to(REPO)}:{call.lineno}: {ast.unparse(call)}")
    assert not found, "\n".join(found)


def _interface() -> list[str]:
    """The members SelectionPolicy states: its attributes and its methods."""
    methods = [k for k, v in vars(SelectionPolicy).items()
               if not k.startswith("_") and (callable(v) or isinstance(v, property))]  # fmt: skip
    return sorted({*SelectionPolicy.__annotations__, *methods})


@pytest.mark.parametrize("name", POLICY_NAMES)
def test_every_policy_has_the_whole_interface(name: str):
    policy = make_policy(name, selection_weight=0.5, bounce_limit=2, explicit=[0])
    members = _interface()
    # The five methods of the rounds and the five things the renderer reads besides.
    assert len(members) == 10, members
    missing = [m for m in members if not hasattr(policy, m)]
    assert not missing
    assert isinstance(policy.observes_fallback_error, bool)
    assert isinstance(policy.follows_budget, bool)
    assert isinstance(policy.needs_calibration, bool)
    assert isinstance(policy.last_frame_note, FrameNote)


class ScriptedPolicy:
    """A SelectionPolicy whose rounds are a script: what the loop asks and tells it is
    logged in ``calls``."""

    follows_budget = True

    def __init__(self, script, observes=False, needs_calibration=False):
        self.script = list(script)
        self.observes_fallback_error = observes
        self.needs_calibration = needs_calibration
        self.last_frame_note = FrameNote()
        self.calls: list = []

    def calibrate(self, samples, rays, pixels, records):
        self.calls.append(("calibrate", samples, rays, pixels, records))
        return (0.5, 0.001)

    def begin_frame(self, view, scene):
        self.calls.append(("begin",))

    def next_round(self, budget):
        self.calls.append(("next_round", budget))
        return self.script.pop(0) if self.script else []

    def round_densities(self, ids):
        return ["full"] * len(ids)

    def record(self, records, seconds):
        self.calls.append(("record", [r.source for r in records], seconds,
                           [r.fallback_error for r in records]))  # fmt: skip

    def end_frame(self):
        self.calls.append(("end",))
        self.last_frame_note = FrameNote(expected_trace_ms=1.5, untraced_reason=None)
        return {}


def _view(pixels) -> FrameView:
    camera = CameraFrame(np.eye(4), focal_length=50.0, horizontal_aperture=36.0, near=0.1, far=1e4)
    return FrameView(0.0, camera, 64, 48, np.asarray(pixels, dtype=np.int64))


def _tracer(rays_per_id: int, ms_per_id: float, log: list):
    def trace(ids, densities):
        log.append(list(ids))
        records = [TraceRecord(e, 10, rays_per_id) for e in ids]
        return TracedRound(records, rays_per_id * len(ids), ms_per_id * len(ids))

    return trace


def test_rounds_trace_only_ids_in_view_not_traced_yet_and_stop_at_the_budget():
    # Element 3 has no pixels, element 1 is asked for twice: neither is traced (again).
    # Rounds charge 100 rays an id against 250: the third round finds 50 left, the
    # fourth none, so the script's last round is never asked for.
    policy = ScriptedPolicy([[1, 3], [1, 2], [0], [4]])
    traced: list = []
    out = run_rounds(policy, _view([5, 5, 5, 0, 5]), None, [0, 1, 2, 4], Budget(rays=250),
                     _tracer(100, 2.0, traced))  # fmt: skip
    assert traced == [[1], [2], [0]]
    assert out.selected == [1, 2, 0] and out.rays == 300 and out.trace_ms == 6.0
    budgets = [c[1] for c in policy.calls if c[0] == "next_round"]
    assert budgets == [Budget(rays=250), Budget(rays=150), Budget(rays=50)]
    records = [c for c in policy.calls if c[0] == "record"]
    assert [r[2] for r in records] == [0.002, 0.002, 0.002]  # the charged ms, in seconds
    assert policy.calls[0] == ("begin",) and policy.calls[-1] == ("end",)
    assert out.starved is None and out.note.expected_trace_ms == 1.5
    assert out.densities == {1: "full", 2: "full", 0: "full"}


def test_a_time_budget_is_charged_the_rounds_time():
    policy = ScriptedPolicy([[0], [1], [2]])
    out = run_rounds(policy, _view([5, 5, 5]), None, [0, 1, 2], Budget(ms=5.0),
                     _tracer(7, 3.0, []))  # fmt: skip
    # 5 ms: a round of 3 ms leaves 2, the second overruns, no third.
    assert out.selected == [0, 1] and out.trace_ms == 6.0
    budgets = [c[1] for c in policy.calls if c[0] == "next_round"]
    assert budgets == [Budget(ms=5.0), Budget(ms=2.0)]


def test_no_budget_with_reflectors_in_view_is_reported_as_starved():
    policy = ScriptedPolicy([[0]])
    traced: list = []
    out = run_rounds(policy, _view([5]), None, [0], Budget(rays=0), _tracer(1, 1.0, traced))
    assert traced == [] and out.starved == Budget(rays=0)
    assert [c[0] for c in policy.calls] == ["begin", "end"]
    # Nothing in view: nothing to explain.
    out = run_rounds(ScriptedPolicy([]), _view([0]), None, [], Budget(rays=0),
                     _tracer(1, 1.0, traced))  # fmt: skip
    assert out.starved is None


@pytest.mark.parametrize(
    ("limits", "visible", "needs", "calibrated"),
    [
        (Budget(ms=10.0), [0], True, True),
        (Budget(ms=10.0), [0], False, False),  # calibrated already
        (Budget(rays=100), [0], True, False),  # not time-budgeted
        (Budget(ms=10.0), [], True, False),  # no reflector in view to time
    ],
)
def test_calibration_runs_once_in_a_time_budgeted_frame_with_reflectors(
    limits, visible, needs, calibrated
):
    policy = ScriptedPolicy([], needs_calibration=needs)
    done = Calibration([(64, 0.2), (512, 0.9)], rays=1700, pixels=1728, wall_ms=3.0)
    out = run_rounds(policy, _view([5 if visible else 0]), None, visible, limits,
                     _tracer(1, 1.0, []), calibrate=lambda: done)  # fmt: skip
    if calibrated:
        assert policy.calls[0] == ("calibrate", done.samples, 1700, 1728, done.records)
        assert policy.calls[1] == ("begin",)  # before the frame's rounds
        assert out.calibration == (done, (0.5, 0.001))
    else:
        assert out.calibration is None
        assert all(c[0] != "calibrate" for c in policy.calls)


@pytest.mark.parametrize("observes", [True, False])
def test_the_fallback_error_is_observed_before_the_policy_learns_only_when_read(observes):
    policy = ScriptedPolicy([[0]], observes=observes)
    last: list = []

    def trace(ids, densities):
        last[:] = [TraceRecord(e, 10, 10) for e in ids]
        return TracedRound(list(last), 10, 1.0)

    def observe():
        for rec in last:
            rec.fallback_error = 0.25

    run_rounds(policy, _view([5]), None, [0], Budget(rays=100), trace, observe=observe)
    recorded = next(c for c in policy.calls if c[0] == "record")
    assert recorded[3] == ([0.25] if observes else [None])


@pytest.mark.slow
def test_a_replay_of_a_capture_selects_what_the_renderer_selects(tmp_path: Path):
    # The replay tool's premise: with a rays budget, the recorded records replayed
    # through the round loop give the selection a render gives, frame by frame.
    stage_path = REPO / "stages" / "sewer.usda"
    frames, width, height = "0:46:2", 96, 72
    recording = tmp_path / "sewer.json.gz"
    policy_replay.capture(stage_path, recording, width, height, frames)
    data = policy_replay.load_recording(recording)
    all_rays = [sum(r.rays for r in f.records.values()) for f in data["frames"]]
    # About half of the busiest frame's rays: HEU1 has to leave some reflectors out.
    budget = max(all_rays) // 2
    replayed, visible = policy_replay.replay(data, "heu1", budget)

    stage = open_stage(stage_path)
    options = RenderOptions(mode="hybrid", heuristic="heu1", width=width, height=height,
                            budget_ms=None, budget_rays=budget,
                            bounce_limit=data["bounce_limit"],
                            selection_weight=data["selection_weight"])  # fmt: skip
    renderer = FrameRenderer(stage, options)
    times = [float(f.view.time) for f in data["frames"]]
    renderer.plan(times)
    refl = data["reflectors"]
    paths = [stage.scene.elements[e].path for e in refl]
    try:
        rendered = np.array([[p in renderer.render(t).stats.selected for p in paths]
                             for t in times])  # fmt: skip
    finally:
        renderer.close()
    assert np.array_equal(rendered, replayed)
    # Not a trivial selection: some frame leaves a reflector in view untraced.
    assert (visible & ~replayed).any() and replayed.any()


def test_replay_needs_a_budget():
    data = {"selection_weight": 0.5, "bounce_limit": 2, "reflectors": [], "frames": [],
            "lights": SimpleNamespace(distant=[], local=[])}  # fmt: skip
    with pytest.raises(ValueError):
        policy_replay.replay(data, "heu1", None)
