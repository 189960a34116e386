"""``phrt sweep`` and its output directory: an earlier sweep is never silently replaced,
``--overwrite`` deletes the sweep's own files only, an interrupted sweep says what it left
(exit 130), an ``--out`` that cannot be made is a bad option (exit 2), and every sweep
records where its figures came from (provenance.json, summary.md, report.html).

The sweeps are tiny (a 32x24 mirror gallery, a few frames) and run through the command
line, as a user runs them.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from repo_paths import REPO
from scenes import mirror_gallery_stage

import phrt_usd
from phrt_usd.engine.renderer import CALIBRATION_SEED
from phrt_usd.errors import BadOption
from phrt_usd.evaluate.image_metrics import FLIP_VIEWING
from phrt_usd.evaluate.sweep_output import SweepDirectory, clear

CLI = [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]
#: A sweep small enough for a test: every configuration of two heuristics at a time and a
#: rays budget (raster, heu1 and heu2 at each budget, all, rt: 7 configurations).
SWEEP_ARGS = ("--resolution", "32x24", "--budgets-ms", "2", "--budgets-rays", "100")
CONFIGS = 7
FIRST_FRAMES = 3
#: The thread setting of the recorded sweep: not the default (the cores), so that the
#: provenance shows the setting given and not a guess.
THREADS = 1


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)


def _one_line_error(done: subprocess.CompletedProcess, code: int) -> str:
    """The stderr of a refused command: exactly one ``error:`` line, no traceback."""
    assert done.returncode == code, (done.returncode, done.stdout[-500:], done.stderr[-2000:])
    assert "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, done.stderr
    return errors[0]


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


@pytest.fixture(scope="module")
def swept(tmp_path_factory) -> tuple[Path, Path]:
    """(stage, OUT) of one finished sweep of FIRST_FRAMES frames."""
    root = tmp_path_factory.mktemp("sweep")
    stage = mirror_gallery_stage(root / "gallery.usda", frames=FIRST_FRAMES)
    out = root / "out"
    done = _cli("sweep", str(stage), "--out", str(out), "--frames", f"1:{FIRST_FRAMES}",
                "--threads", str(THREADS), *SWEEP_ARGS)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    return stage, out


@pytest.mark.slow
def test_probe_sweep_into_non_empty_out_replaces_earlier_sweep(swept, tmp_path):
    """A second sweep into the OUT of a first is refused (one line, exit 2; with --json
    one JSON object; also before a cluster would start) and the first sweep's files stay
    byte for byte. ``--overwrite`` replaces the sweep's own files only: a user's file, a
    directory of theirs among the images and the target of a planted link all stay."""
    stage, first = swept
    out = tmp_path / "out"
    shutil.copytree(first, out, symlinks=True)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    again = ("sweep", str(stage), "--out", str(out), "--frames", "1:2", *SWEEP_ARGS)

    line = _one_line_error(_cli(*again), 2)
    assert "not empty" in line and "--overwrite" in line
    error = json.loads(_cli(*again, "--json").stdout)
    assert error["code"] == 2 and "not empty" in error["error"]
    # The cluster path claims OUT before any cluster starts.
    assert "not empty" in _one_line_error(_cli(*again, "--workers", "1"), 2)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before

    outside = tmp_path / "precious.png"
    outside.write_bytes(b"not the sweep's")
    (out / "timeline_planted.png").symlink_to(outside)  # a sweep's name, planted as a link
    (out / "notes.txt").write_text("mine")
    (out / "images" / "gallery" / "keep").mkdir()
    (out / "images" / "gallery" / "keep" / "notes.txt").write_text("mine too")
    stale = out / "images" / "gallery" / "99"
    stale.mkdir()
    (stale / "raster.png").write_bytes(before["error_vs_time.png"])

    done = _cli(*again, "--overwrite")
    assert done.returncode == 0, done.stderr[-2000:]
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "images" / "gallery" / "keep" / "notes.txt").read_text() == "mine too"
    assert outside.read_bytes() == b"not the sweep's"
    assert not (out / "timeline_planted.png").is_symlink()
    assert not stale.exists()  # the earlier sweep's frame images are gone with it
    assert len(_csv_rows(out / "sweep.csv")) == 2 * CONFIGS  # the new sweep's 2 frames


def test_overwrite_never_follows_links(tmp_path):
    """``clear`` removes links themselves: an ``images`` link to another directory, or a
    stage directory that is a link, leaves what they point to untouched."""
    elsewhere = tmp_path / "elsewhere"
    (elsewhere / "1").mkdir(parents=True)
    (elsewhere / "1" / "raster.png").write_bytes(b"x")
    out = tmp_path / "out"
    out.mkdir()
    (out / "images").symlink_to(elsewhere, target_is_directory=True)
    (out / "sweep.csv").write_text("a\n")
    clear(out)
    assert not (out / "images").exists() and not (out / "sweep.csv").exists()
    assert (elsewhere / "1" / "raster.png").read_bytes() == b"x"

    (out / "images").mkdir()
    (out / "images" / "stage").symlink_to(elsewhere, target_is_directory=True)
    clear(out)
    assert (elsewhere / "1" / "raster.png").read_bytes() == b"x"


def test_an_out_holding_only_the_sweeps_inputs_is_taken(tmp_path):
    """paper.json is an input a user puts in OUT before the sweep: not a reason to refuse."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "paper.json").write_text("{}")
    with SweepDirectory(out):
        pass
    (out / "summary.md").write_text("earlier")
    with pytest.raises(BadOption, match="not empty"), SweepDirectory(out):
        pass
    with SweepDirectory(out, overwrite=True):
        assert sorted(p.name for p in out.iterdir()) == [".phrt.lock", "paper.json"]


@pytest.mark.slow
def test_probe_unwritable_output_in_sweep_exits_1(swept, tmp_path):
    """An --out that cannot be made is a bad option: exit 2, one line naming --out,
    before any frame renders (no traceback, no partial directory)."""
    stage, _out = swept
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for out, reason in (
        (a_file / "sub", "cannot create"),  # under a file
        (Path("/proc/phrt-sweep-out"), "cannot create"),  # where nothing can be made
        (a_file, "not a directory"),
    ):
        line = _one_line_error(_cli("sweep", str(stage), "--out", str(out), *SWEEP_ARGS), 2)
        assert f"--out {out}" in line and reason in line, line
    error = json.loads(_cli("sweep", str(stage), "--out", str(a_file / "sub"), "--json",
                            *SWEEP_ARGS).stdout)  # fmt: skip
    assert error["code"] == 2 and "cannot create" in error["error"]


@pytest.mark.slow
def test_probe_interrupted_sweep_says_wrote_n_rows(tmp_path):
    """SIGINT during a long sweep: exit 130 and one line that says it was interrupted,
    after how many of how many frames, and what OUT holds (the finished frames' rows and
    report), never "wrote N rows" as if it had finished."""
    frames = 400  # far more than run before the signal lands (~0.1 s a frame here)
    stage = mirror_gallery_stage(tmp_path / "long.usda", frames=frames)
    out = tmp_path / "out"
    command = [*CLI, "sweep", str(stage), "--out", str(out), "--frames", f"1:{frames}",
               "--heuristics", "heu1", "--resolution", "32x24",
               "--budgets-rays", "100"]  # fmt: skip
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and process.poll() is None:
            csv_path = out / "sweep.csv"
            if csv_path.is_file() and len(csv_path.read_text().splitlines()) > 1:
                break
            time.sleep(0.05)
        assert process.poll() is None, "the sweep ended before it could be interrupted"
        process.send_signal(signal.SIGINT)
        stdout, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    done = subprocess.CompletedProcess(command, process.returncode, stdout, stderr)
    line = _one_line_error(done, 130)
    assert "wrote" not in stdout
    rows = _csv_rows(out / "sweep.csv")
    configs = 4  # raster, heu1@100rays, all, rt
    finished = len(rows) // configs
    assert len(rows) == finished * configs and 1 <= finished < frames
    assert line.startswith(f"error: interrupted: stopped after {finished} of {frames} frames")
    assert f"({len(rows)} rows)" in line and "--overwrite" in line
    for name in ("summary.md", "report.html", "provenance.json"):
        assert (out / name).is_file(), name
    assert json.loads((out / "provenance.json").read_text())["settings"]["interrupted"] is True


def _git_head() -> str:
    done = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True,
                          text=True, check=False)  # fmt: skip
    return done.stdout.strip() if done.returncode == 0 else "unknown"


@pytest.mark.slow
def test_sweep_records_its_provenance(swept):
    """provenance.json holds what reproducing and citing the sweep needs, and summary.md
    and report.html show it; report.html links the CSVs."""
    stage, out = swept
    record = json.loads((out / "provenance.json").read_text())
    assert record["phrt_version"] == phrt_usd.__version__
    assert record["commit"] == (_git_head() if (REPO / ".git").exists() else "unknown")
    assert "sweep" in record["command"] and str(stage) in record["command"]
    assert "--budgets-rays 100" in record["command"]
    assert record["machine"]["cores"] == os.cpu_count()
    assert record["machine"]["cpu"] and record["machine"]["cpu"] != "unknown"
    assert record["threads"]["setting"] == THREADS
    assert record["gl"]["requested"] == "auto" and record["gl"]["platform"] in ("egl", "osmesa")
    flip = record["metric"]["flip"]
    viewing = [flip["monitor_distance_m"], flip["monitor_resolution_x"], flip["monitor_width_m"]]
    assert viewing == list(FLIP_VIEWING)
    # FLIP's documented default, 67 pixels per degree, to its 4 printed digits.
    assert flip["pixels_per_degree"] == pytest.approx(67.02, abs=0.005)
    assert record["seeds"] == {"calibration": CALIBRATION_SEED}
    assert record["settings"]["stages"] == [str(stage)]

    summary = (out / "summary.md").read_text()
    html = (out / "report.html").read_text()
    for text in (summary, html):
        assert record["commit"] in text and record["machine"]["cpu"] in text
        assert record["command"] in text.replace("&#x27;", "'") and "67.02" in text
    assert 'href="sweep.csv"' in html and 'href="summary.csv"' in html


@pytest.mark.slow
def test_sweep_summary_gives_spread_and_budget_adherence(swept):
    """summary.csv: per config the mean, median, p5 and p95 of frame time and FLIP, ordered
    (p5 <= median <= p95, the mean inside [p5 - span, p95 + span]); the share of frames
    within budget for budgeted configs (a share) and none for the others."""
    _stage, out = swept
    rows = {r["config"]: r for r in _csv_rows(out / "summary.csv")}
    for config, row in rows.items():
        for stem in ("frame_ms", "flip"):
            p5, median, p95 = (float(row[f"{q}_{stem}"]) for q in ("p5", "median", "p95"))
            assert p5 <= median <= p95, (config, stem)
            # Three frames: the mean lies within [min, max], and p5 / p95 (linear) are
            # within 10 % of the range of min / max, so within one band width of them.
            mean = float(row[f"mean_{stem}"])
            span = p95 - p5
            assert p5 - span <= mean <= p95 + span, (config, stem)
        budgeted = config.startswith(("heu1@", "heu2@"))
        assert (row["budget_within"] != "") == budgeted, config
        if budgeted:
            assert 0.0 <= float(row["budget_within"]) <= 1.0
            assert row["budget_checked"] == ("rays" if config.endswith("rays") else "time")


def test_a_sweep_interrupted_before_its_first_frame_says_it_left_no_results(tmp_path):
    """No finished frame: no report to make (not an error about an empty sweep.csv), and
    the line says OUT holds no results."""
    from phrt_usd.evaluate.sweep import SweepSpec, finish_sweep, interruption_note

    out = tmp_path / "out"
    out.mkdir()
    spec = SweepSpec(stages=[tmp_path / "farm.usda"], heuristics=["heu1"],
                     budgets_rays=[100], out=out)  # fmt: skip
    summary = finish_sweep(spec, [], {}, interrupted=True)
    summary["frames"] = {}
    assert summary["files"] == ["sweep.csv", "timeline.json", "provenance.json"]
    assert not (out / "report.html").exists()
    note = interruption_note(summary)
    assert note.startswith("stopped after no frame (not started: farm);")
    assert "holds no results" in note
