"""Reuse across frames (``engine/reflection_history.py``): a still view at a reduced
density converges to full density within its rotation period, a moved object leaves no
ghost after the frames the rejection rule allows, and reuse never makes a moving
sequence worse than filling alone."""

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom
from scenes import mirror_floor_stage, mirror_gallery_stage

from phrt_usd.engine import reflection_history
from phrt_usd.engine.renderer import FrameRenderer, RenderOptions
from phrt_usd.engine.trace.sparse_pixels import ROTATION_PERIOD
from phrt_usd.evaluate.image_metrics import flip_map
from phrt_usd.model import pixel_kinds
from phrt_usd.usd.stage import open_stage

W, H = 160, 120


def _options(density: str) -> RenderOptions:
    return RenderOptions(mode="hybrid", heuristic="all", budget_ms=None, width=W, height=H,
                         trace_density=density)  # fmt: skip


def _sequence(stage, times, density: str):
    """The frames of ``times`` rendered in order at ``density`` by one renderer."""
    renderer = FrameRenderer(stage, _options(density))
    try:
        renderer.plan(times)
        return [renderer.render(t) for t in times]
    finally:
        renderer.close()


def _checker_wall(stage, cells: int = 24, size: float = 0.25) -> None:
    """A wall of ``cells`` x ``cells`` squares of ``size`` m, alternating white and
    dark, standing on the floor behind the ball (z = -2): detail at every scale of the
    reflection, which a fill from a sixteenth of the pixels cannot keep."""
    mesh = UsdGeom.Mesh.Define(stage, "/World/Checker")
    points, counts, indices, colors = [], [], [], []
    for i in range(cells):
        for j in range(cells):
            x0, y0 = (i - cells / 2) * size, j * size
            base = len(points)
            points += [(x0, y0, -2.0), (x0 + size, y0, -2.0), (x0 + size, y0 + size, -2.0),
                       (x0, y0 + size, -2.0)]  # fmt: skip
            counts.append(4)
            indices += [base, base + 1, base + 2, base + 3]
            colors.append((0.9, 0.9, 0.9) if (i + j) % 2 else (0.05, 0.05, 0.1))
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(indices)
    color = mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.uniform)
    color.Set(colors)


def _still_stage(tmp_path, frames: int):
    """The mirror floor and a checker wall, a still camera over ``frames`` time codes."""
    path = mirror_floor_stage(tmp_path / "floor.usda", W, H)
    stage = Usd.Stage.Open(str(path))
    _checker_wall(stage)
    stage.SetEndTimeCode(frames)
    stage.GetRootLayer().Save()
    return open_stage(path)


@pytest.mark.parametrize("density", ["half", "quarter", "sixteenth"])
def test_still_view_converges_to_full_density_within_its_period(tmp_path, density):
    period = ROTATION_PERIOD[density]
    times = [float(t) for t in range(1, period + 2)]
    stage = _still_stage(tmp_path, len(times))
    full = _sequence(stage, times[:1], "full")[0].beauty
    frames = _sequence(stage, times, density)
    first = flip_map(full, frames[0].beauty).mean()
    last = frames[period - 1]
    # Frame `period` has traced every pixel of the floor once in the last `period`
    # frames: what a full-density frame traced. 0.02 is the suite's "same image" FLIP
    # (image_thresholds); the first frame (fill only) is above it at a sixteenth.
    assert flip_map(full, last.beauty).mean() <= 0.02
    # Every floor pixel but those whose history the range test refuses (a detail no
    # traced sample around it shows this frame: a few pixels of the checker's corners)
    # is traced or reused: 1 % of the floor at most.
    kinds = last.stats.pixel_kinds
    assert kinds["filled"] <= 0.01 * (kinds["filled"] + kinds["reused"] + kinds["traced"])
    assert kinds["reused"] > 0
    # Monotone in the mean: every frame keeps what the earlier ones traced.
    errors = [flip_map(full, f.beauty).mean() for f in frames[:period]]
    assert errors[-1] <= first
    # 1e-3: the noise of FLIP's mean between two frames of the same quality.
    assert all(b <= a + 1e-3 for a, b in zip(errors, errors[1:], strict=False))


def test_sixteenth_reaches_the_target_in_16_frames(tmp_path):
    """The stated target: a sixteenth density, FLIP <= 0.02 against full within 16."""
    times = [float(t) for t in range(1, 17)]
    stage = _still_stage(tmp_path, len(times))
    full = _sequence(stage, times[:1], "full")[0].beauty
    frames = _sequence(stage, times, "sixteenth")
    assert flip_map(full, frames[0].beauty).mean() > 0.02  # the target is not trivial
    assert min(flip_map(full, f.beauty).mean() for f in frames) <= 0.02


def _moving_ball_stage(tmp_path, stop: int, frames: int):
    """The mirror floor, still camera, the ball sliding 1.5 m along x from frame 1 to
    ``stop``, then still until ``frames``."""
    path = mirror_floor_stage(tmp_path / "moving.usda", W, H)
    stage = Usd.Stage.Open(str(path))
    ball = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Ball"))
    (op,) = ball.GetOrderedXformOps()
    start = op.Get()
    op.GetAttr().Clear()
    op.Set(start, 1.0)
    op.Set(start + Gf.Vec3d(1.5, 0.0, 0.0), float(stop))
    stage.SetEndTimeCode(frames)
    stage.GetRootLayer().Save()
    return open_stage(path)


def _ghosts(reused, full, moved_away, frames, kind=pixel_kinds.REUSED) -> list[int]:
    """Per frame of ``frames``: the pixels of ``moved_away`` that show the ball where it
    was. A ghost is history showing what is no longer there: a REUSED pixel that differs
    from full density by more than 0.05 in linear radiance (an eighth of the ball's red
    against the floor's grey); filled pixels are this frame's reconstruction (no history
    in them, but the share ``accumulate`` blends in), traced ones exact. ``kind``: the
    pixels counted (REUSED; FILLED for the accumulation's)."""
    counts = []
    for k in frames:
        diff = np.abs(reused[k].beauty - full[k].beauty).max(axis=2)
        ghost = moved_away & (reused[k].pixel_kind == kind) & (diff > 0.05)
        counts.append(int(ghost.sum()))
    return counts


def test_moved_object_leaves_no_ghost_after_the_period(tmp_path, monkeypatch):
    period = ROTATION_PERIOD["sixteenth"]
    stop, frames = 8, 8 + period + 1
    stage = _moving_ball_stage(tmp_path, stop, frames)
    times = [float(t) for t in range(1, frames + 1)]
    full = _sequence(stage, times, "full")
    floor = full[0].gbuffer.element_id == full[0].gbuffer.element_id[H - 1, W // 2]
    # The old reflection's pixels: where the first frame's reflection differs from the
    # last one's (the ball has moved away from them).
    moved_away = floor & (np.abs(full[0].beauty - full[-1].beauty).max(axis=2) > 0.05)
    assert moved_away.sum() > 20  # the ball's reflection moved by many pixels
    after = range(stop, frames)
    stale = _ghosts(_sequence(stage, times, "sixteenth"), full, moved_away, after)
    # The age limit: nothing traced before the ball stopped survives `period` frames.
    assert stale[period - 1 :] == [0] * (len(stale) - period + 1), stale
    # The gradient and range tests reject most of it sooner: 4 frames after the stop,
    # under half the ghost pixels that the age limit alone leaves.
    monkeypatch.setattr(reflection_history, "GRADIENT_LIMIT", np.inf)
    monkeypatch.setattr(reflection_history, "RANGE_TOLERANCE", 1e30)  # no range test
    unguarded = _ghosts(_sequence(stage, times, "sixteenth"), full, moved_away, after)
    assert sum(unguarded[4:period - 1]) > 0, unguarded  # the comparison is not empty
    assert sum(stale[4:period - 1]) <= 0.5 * sum(unguarded[4:period - 1]), (stale, unguarded)


def test_accumulated_fills_leave_no_ghost_of_a_moved_object(tmp_path, monkeypatch):
    """A filled pixel blends in its previous value clamped to the range of the samples
    its fill was made of: where the ball moved away, those samples show the floor, so
    the ball's old colour is clamped out. Over the frames after the ball stops, the
    filled pixels that differ from full density by a ghost's margin are no more than
    without the accumulation (the fill's own errors), plus 5 % of them (the clamp keeps
    history within the samples' range, and a range that still holds some of the ball's
    red near its new place lets a little through)."""
    stop, frames = 8, 16
    stage = _moving_ball_stage(tmp_path, stop, frames)
    times = [float(t) for t in range(1, frames + 1)]
    full = _sequence(stage, times, "full")
    floor = full[0].gbuffer.element_id == full[0].gbuffer.element_id[H - 1, W // 2]
    moved_away = floor & (np.abs(full[0].beauty - full[-1].beauty).max(axis=2) > 0.05)
    after = range(stop, frames)
    kept = _ghosts(_sequence(stage, times, "sixteenth"), full, moved_away, after,
                   pixel_kinds.FILLED)  # fmt: skip
    monkeypatch.setattr(reflection_history, "ACCUMULATION", 0.0)
    plain = _ghosts(_sequence(stage, times, "sixteenth"), full, moved_away, after,
                    pixel_kinds.FILLED)  # fmt: skip
    assert sum(kept) <= 1.05 * sum(plain) + 1, (kept, plain)


@pytest.mark.slow
def test_moving_camera_reuse_is_no_worse_than_filling(tmp_path, monkeypatch):
    """The gallery's moving camera: with reuse the sequence's mean FLIP against full
    density is at most filling alone's (reuse takes only history the tests keep)."""
    # A slow pan (the 40-frame path over 800 frames: under a quarter pixel a frame), so
    # most reprojected points land near a pixel centre and history is taken.
    stage = open_stage(mirror_gallery_stage(tmp_path / "gallery.usda", frames=800, width=W,
                                            height=H))  # fmt: skip
    times = [float(t) for t in range(200, 216)]
    full = _sequence(stage, times, "full")
    reused = _sequence(stage, times, "sixteenth")
    monkeypatch.setattr(reflection_history.ReflectionHistory, "end", lambda self, reuse: None)
    filled = _sequence(stage, times, "sixteenth")
    err_reuse = np.mean([flip_map(a.beauty, b.beauty).mean()
                         for a, b in zip(full, reused, strict=True)])  # fmt: skip
    err_fill = np.mean([flip_map(a.beauty, b.beauty).mean()
                        for a, b in zip(full, filled, strict=True)])  # fmt: skip
    assert err_reuse <= err_fill * 1.01  # 1 %: FLIP's mean over a few pixels' noise
    kinds = reused[-1].pixel_kind
    assert (kinds == pixel_kinds.REUSED).any()
