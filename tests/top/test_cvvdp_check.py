"""tools/cvvdp_check.py without cvvdp: its Spearman helper, its one-line failure when
cvvdp is not importable (the project's env has no torch), and its ``alternate`` and
``ours`` steps on two render outputs made here.

The outputs: 4 frames of 32 x 24 of a still scene (a grey gradient) with one reflector
patch (rows 6-17, columns 8-23) that two reflectors /A and /B share; ``all`` draws the
patch at 0.8 (traced), ``none`` at 0.2 (raster fallback). Both reflectors are visible in
every frame, ``all`` selects both, ``none`` neither. The frames carry their motion (0:
the scene is still), as ``--aovs motion`` writes it. So, exactly: ``none``'s error is the
same in every frame and its temporal error is 0 (a steady error is not popping), and
the alternating sequence (all, none, all, none) has half its per-frame FLIP (two frames
exact, two equal to ``none``'s), a positive temporal error, and 2 reflectors x 3 switches
= 6 transitions.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from repo_paths import TOOLS

from phrt_usd.run.images import write_frame_exr, write_preview_png

sys.path.insert(0, str(TOOLS))
import cvvdp_check  # noqa: E402

W, H, FRAMES = 32, 24, 4
REFLECTORS = ["/A", "/B"]


def _render_dir(root: Path, name: str, patch: float, heuristic: str, motion=True) -> Path:
    out = root / name
    (out / "frames").mkdir(parents=True)
    beauty = np.repeat(np.linspace(0.1, 0.6, W, dtype=np.float32)[None, :, None], H, 0)
    beauty = np.repeat(beauty, 3, axis=2)
    beauty[6:18, 8:24] = patch
    ids = np.full((H, W), -1, dtype=np.int32)
    ids[6:18, 8:24] = 0
    frames = []
    for f in range(FRAMES):
        stem = f"{241 + f:04d}"
        if motion:
            still = np.zeros((H, W, 2), np.float32)
            cvvdp_check.write_frame(out / "frames" / f"{stem}.exr", beauty, ids, still)
        else:
            write_frame_exr(out / "frames" / f"{stem}.exr", beauty, np.ones((H, W)),
                            np.full((H, W), 2.0), ids, ids >= 0)
        write_preview_png(out / "frames" / f"{stem}.png", beauty)
        frames.append({"time": float(241 + f), "frame_ms": 10.0,
                       "rays": 100 if heuristic == "all" else 0,
                       "visible": REFLECTORS,
                       "selected": REFLECTORS if heuristic == "all" else []})
    run = {"stage": "synthetic.usda", "heuristic": heuristic, "budget_ms": None,
           "budget_rays": None, "resolution": [W, H], "frame_range": [241.0, 244.0],
           "time_codes_per_second": 24.0, "reflectors": REFLECTORS}
    (out / "stats.json").write_text(json.dumps({"run": run, "frames": frames}))
    return out


def test_spearman_ranks_ties_and_undefined():
    assert cvvdp_check.spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert cvvdp_check.spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)
    # ties share their mean rank: ranks (1, 2.5, 2.5, 4) against (1, 2, 3, 4) give
    # 4.5 / sqrt(4.5 * 5) (centred ranks), computed by hand
    assert cvvdp_check.spearman([1, 2, 2, 3], [1, 2, 3, 4]) == pytest.approx(
        4.5 / np.sqrt(22.5), abs=1e-12)
    assert cvvdp_check.spearman([1, 1, 1], [1, 2, 3]) is None  # constant sample
    assert cvvdp_check.spearman([1, 2], [1, 2]) is None  # too few values


def test_cvvdp_step_without_cvvdp_fails_with_one_line(tmp_path):
    ours = tmp_path / "ours.json"
    ours.write_text("{}")
    done = subprocess.run([sys.executable, str(TOOLS / "cvvdp_check.py"), "cvvdp", str(ours)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot import" in lines[0], done.stderr


@pytest.mark.slow
def test_alternate_and_ours_on_synthetic_outputs(tmp_path):
    ref = _render_dir(tmp_path, "all", 0.8, "all")
    none = _render_dir(tmp_path, "none", 0.2, "none")
    alt = tmp_path / "alt"
    cvvdp_check.main(["alternate", str(ref), str(none), "--out", str(alt)])
    out = tmp_path / "ours.json"
    cvvdp_check.main(["ours", str(ref), str(ref), str(none), str(alt), "--out", str(out)])
    result = json.loads(out.read_text())
    assert result["frames_per_second"] == 24.0
    same, steady, popping = result["configs"]
    assert same["flip"] == 0.0 and same["temporal_error"] == 0.0 and same["transitions"] == 0
    # A still, steady error: no popping (nothing changes from frame to frame).
    assert steady["flip"] > 0.0
    assert steady["temporal_error"] == 0.0
    assert steady["transitions"] == 0
    assert popping["flip"] == pytest.approx(steady["flip"] / 2, rel=1e-6)
    # a 0.2 -> 0.8 switch of a quarter of the frame every frame: each switch is popping
    # where the reference does not change, far above float noise (measured 0.12)
    assert popping["temporal_error"] > 0.01
    assert popping["transitions"] == len(REFLECTORS) * (FRAMES - 1)


@pytest.mark.slow
def test_synthetic_sequences_are_render_outputs(tmp_path):
    """The ``synthetic`` step writes the six sequences as render outputs: the patch's
    linear radiance is what each sequence promises in the frames checked."""
    from phrt_usd.run.images import read_frame_exr

    cvvdp_check.main(["synthetic", "--out", str(tmp_path)])
    names = ("reference", "steady", "blend", "pop1", "pop2", "pop4")
    for name in names:
        stats = json.loads((tmp_path / name / "stats.json").read_text())
        assert len(stats["frames"]) == cvvdp_check.SYNTHETIC_FRAMES
    def patch(name, frame):
        exr = read_frame_exr(tmp_path / name / "frames" / f"{frame:04d}.exr")["beauty"]
        ref = read_frame_exr(tmp_path / "reference" / "frames" / f"{frame:04d}.exr")["beauty"]
        return float((exr - ref)[120, 160, 0])  # the middle of the 320x240 frame

    p, half = cvvdp_check.SYNTHETIC_PATCH, 1e-3  # the beauty is stored in half floats
    assert patch("steady", 1) == pytest.approx(p, abs=half)
    assert patch("blend", 1) == pytest.approx(p / 2, abs=half)
    # pop2: off in frames 1-2 (t = 0, 1), on in frames 3-4
    assert patch("pop2", 2) == 0.0 and patch("pop2", 3) == pytest.approx(p, abs=half)


@pytest.mark.slow
def test_ours_needs_the_reference_motion(tmp_path):
    """A reference rendered without ``--aovs motion``: one line naming the frame and the
    option, exit 2."""
    ref = _render_dir(tmp_path, "all", 0.8, "all", motion=False)
    done = subprocess.run([sys.executable, str(TOOLS / "cvvdp_check.py"), "ours", str(ref),
                           str(ref), "--out", str(tmp_path / "o.json")],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--aovs motion" in lines[0], done.stderr
