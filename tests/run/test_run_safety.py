"""A render never loses, mixes or runs what is in its output directory.

Each test plants what a careless pipeline or a hostile run directory could hold (pickles,
symlinks, an earlier run, a second render, a full disk, a kill -9) and checks that phrt
refuses with one line or carries on without touching anything outside ``OUT``.
"""

from __future__ import annotations

import json
import os
import pickle
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from scenes import mirror_gallery_stage

from phrt_usd.api import run_render
from phrt_usd.atomic import WriteFailed, write_text_atomic
from phrt_usd.engine.renderer import RenderOptions
from phrt_usd.errors import BadOption, PhrtError
from phrt_usd.run.render_job import RenderJob
from phrt_usd.run.run_directory import DirectoryLock
from phrt_usd.run.run_files import CHECKPOINT_FILE, LOCK_FILE, RESERVE_FILE

OPTIONS = RenderOptions(width=32, height=24, budget_ms=None, budget_rays=600)
CLI = [sys.executable, "-m", "typer", "phrt_usd.cli", "run"]
#: Names a run directory holds, where something may be planted.
RUN_NAMES = ("stats.json", "selection.usda", CHECKPOINT_FILE, "checkpoint.pkl",
             "frames/0001.exr", "frames/0001.png")  # fmt: skip


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=timeout)


def _one_line_error(done: subprocess.CompletedProcess, code: int) -> str:
    """The stderr of a refused command: exactly one ``error:`` line, no traceback."""
    assert done.returncode == code, (done.returncode, done.stderr)
    assert "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1, done.stderr
    return errors[0]


class _Planted:
    """Unpickling this creates ``marker``: proof that a pickle was executed."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


@pytest.fixture(scope="module")
def gallery(tmp_path_factory) -> Path:
    return mirror_gallery_stage(tmp_path_factory.mktemp("stage") / "gallery.usda", frames=4)


def _job(stage: Path, out: Path, **kw) -> RenderJob:
    return RenderJob(stage_path=stage, out_dir=out, options=OPTIONS, frames="1:3", **kw)


# --- code from data --------------------------------------------------------------------


@pytest.mark.slow
def test_planted_pickles_under_every_name_never_run(gallery, tmp_path):
    """A pickle at any name phrt reads in OUT (checkpoint, stats, layer, old checkpoint
    name) is refused as unreadable and never unpickled, by --resume and by report."""
    marker = tmp_path / "executed"
    for name in RUN_NAMES:
        out = tmp_path / name.replace("/", "_")
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_bytes(pickle.dumps(_Planted(marker)))
        resumed = _cli("render", str(gallery), "--out", str(out), "--frames", "1:2",
                       "--budget-rays", "600", "--resolution", "32x24", "--resume")  # fmt: skip
        _one_line_error(resumed, 1)
        report = _cli("report", str(out))
        assert report.returncode in (0, 2), report.stderr
        assert "Traceback" not in report.stderr
        assert not marker.exists(), f"a pickle at {name} was executed"


# --- symlinks ---------------------------------------------------------------------------


@pytest.mark.slow
def test_planted_symlinks_are_never_followed(gallery, tmp_path):
    """Links at every name in OUT point at a victim file and folder outside it: a render
    refuses the non-empty OUT, and with --overwrite removes the links themselves and
    writes real files; the victims are byte-identical afterwards."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    victim_dir = tmp_path / "victim_dir"
    victim_dir.mkdir()
    (victim_dir / "keep.txt").write_text("keep\n")
    out = tmp_path / "out"
    (out / "frames").mkdir(parents=True)
    for name in RUN_NAMES:
        (out / name).symlink_to(victim)

    with pytest.raises(PhrtError, match="not empty"):
        run_render(_job(gallery, out))
    run_render(_job(gallery, out, overwrite=True))
    assert victim.read_text() == "precious\n"
    for name in ("stats.json", "selection.usda", CHECKPOINT_FILE, "frames/0001.exr"):
        assert not (out / name).is_symlink() and (out / name).stat().st_size > 0, name

    # A linked frames folder or lock file is refused, not written through.
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / "frames").symlink_to(victim_dir, target_is_directory=True)
    with pytest.raises(PhrtError):
        run_render(_job(gallery, linked, resume=True))
    locked = tmp_path / "locked"
    locked.mkdir()
    (locked / LOCK_FILE).symlink_to(victim)
    with pytest.raises(PhrtError, match="symlink"):
        run_render(_job(gallery, locked))
    assert victim.read_text() == "precious\n"
    assert sorted(p.name for p in victim_dir.iterdir()) == ["keep.txt"]


def test_atomic_writer_never_writes_through_a_link(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    final = tmp_path / "stats.json"
    final.symlink_to(victim)
    write_text_atomic(final, "{}\n")
    assert not final.is_symlink() and final.read_text() == "{}\n"
    assert victim.read_text() == "precious\n"


# --- an existing run directory ----------------------------------------------------------


@pytest.mark.slow
def test_existing_out_is_refused_unless_resume_or_overwrite(gallery, tmp_path):
    out = tmp_path / "out"
    run_render(_job(gallery, out))
    (out / "notes.txt").write_text("mine\n")
    with pytest.raises(PhrtError, match="not empty"):
        run_render(_job(gallery, out))
    run_render(_job(gallery, out, resume=True))  # the same run: nothing left to do
    other = RenderJob(stage_path=gallery, out_dir=out, options=OPTIONS, frames="1:2")
    with pytest.raises(PhrtError, match="frame list"):
        run_render(RenderJob(**{**other.__dict__, "resume": True}))
    run_render(RenderJob(**{**other.__dict__, "overwrite": True}))
    stats = json.loads((out / "stats.json").read_text())
    assert [f["time"] for f in stats["frames"]] == [1.0, 2.0]
    assert sorted(p.name for p in (out / "frames").iterdir()) == [
        "0001.exr", "0001.png", "0002.exr", "0002.png"]  # fmt: skip
    assert (out / "notes.txt").read_text() == "mine\n"  # not phrt's: kept


@pytest.mark.slow
def test_probe_overwrite_deletes_only_phrts_own_files(gallery, tmp_path):
    """--overwrite deletes only what this run's names make (known names and extensions
    inside OUT), never what a run file names: a stats.json edited to list other files, a
    folder reached through a link out of OUT, and folders phrt did not make all stay."""
    out = tmp_path / "out"
    run_render(_job(gallery, out))  # frames 1:3, the default layout
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "0001.exr").write_text("theirs\n")
    (tmp_path / "victim.0001.exr").write_text("theirs\n")
    (out / "plate.exr").write_text("mine\n")  # a user's file with an image's extension
    (out / "mine").mkdir()  # an empty folder phrt did not make
    (out / "frames" / ".keep").write_text("")  # a hidden file that is no temp file of ours
    (out / "linked").symlink_to(outside, target_is_directory=True)
    stats = json.loads((out / "stats.json").read_text())
    listed = ("plate.exr", "mine/x.$F4.exr", "linked/$F4.exr", "../victim.$F4.exr")
    stats["run"]["products"] = {name: {"channels": [], "multipart": False} for name in listed}
    (out / "stats.json").write_text(json.dumps(stats))

    run_render(RenderJob(**{**_job(gallery, out).__dict__, "frames": "1", "overwrite": True}))
    assert (out / "plate.exr").read_text() == "mine\n"
    assert (out / "mine").is_dir() and (out / "frames" / ".keep").exists()
    assert (outside / "0001.exr").read_text() == "theirs\n"
    assert (tmp_path / "victim.0001.exr").read_text() == "theirs\n"
    # phrt's own: this run's names at any frame number, and its run files, rewritten
    assert sorted(p.name for p in (out / "frames").iterdir()) == [".keep", "0001.exr", "0001.png"]
    assert [f["time"] for f in json.loads((out / "stats.json").read_text())["frames"]] == [1.0]


@pytest.mark.slow
def test_resume_knows_the_run_by_content(gallery, tmp_path):
    """The same stage under another name resumes; an edited stage does not."""
    out = tmp_path / "out"
    run_render(_job(gallery, out))
    alias = tmp_path / "alias.usda"
    alias.symlink_to(gallery)
    run_render(_job(alias, out, resume=True))
    edited = tmp_path / "edited.usda"
    edited.write_text(gallery.read_text().replace("(0.01, 100)", "(0.02, 100)"))
    assert edited.read_text() != gallery.read_text()
    with pytest.raises(PhrtError, match="layers changed"):
        run_render(_job(edited, out, resume=True))


def test_selection_layer_may_not_name_a_stage_layer(gallery, tmp_path):
    before = gallery.read_bytes()
    with pytest.raises(BadOption, match="layer of the stage"):
        run_render(_job(gallery, tmp_path / "out", selection_layer=gallery))
    assert gallery.read_bytes() == before


@pytest.mark.slow
def test_a_second_render_into_a_locked_out_is_refused(gallery, tmp_path):
    stage = mirror_gallery_stage(tmp_path / "long.usda", frames=400)
    out = tmp_path / "out"
    first = subprocess.Popen([*CLI, "render", str(stage), "--out", str(out), "--frames",
                              "1:400", "--budget-rays", "600", "--resolution", "32x24"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not (out / "frames").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        second = _cli("render", str(stage), "--out", str(out), "--frames", "1:2",
                      "--budget-rays", "600", "--resolution", "32x24", "--resume")  # fmt: skip
        line = _one_line_error(second, 1)
        assert f"pid {first.pid}" in line
    finally:
        first.kill()
        first.wait()
    # The kernel released the killed holder's lock: the next render may take over.
    run_render(RenderJob(stage_path=stage, out_dir=out, options=OPTIONS, frames="1:2",
                         overwrite=True))  # fmt: skip


@pytest.mark.slow
def test_probe_hard_link_as_lock_or_reserve_is_never_written(gallery, tmp_path):
    """A hard link to another file planted as OUT/.phrt.lock or OUT/.phrt.reserve (a dead
    run's name, so a render takes the directory over) is replaced, never written: the
    linked file keeps its bytes and size, and keeps no name in OUT."""
    for name in (LOCK_FILE, RESERVE_FILE):
        victim = tmp_path / f"victim{name}"
        victim.write_bytes(b"precious\n")
        out = tmp_path / f"out{name}"
        out.mkdir()
        os.link(victim, out / name)
        run_render(_job(gallery, out))
        assert victim.read_bytes() == b"precious\n", name
        assert victim.stat().st_nlink == 1, name  # the planted name was removed, not reused
    # The lock alone (a sweep takes it too): the planted file is replaced while held.
    victim = tmp_path / "victim"
    victim.write_bytes(b"precious\n")
    out = tmp_path / "swept"
    out.mkdir()
    os.link(victim, out / LOCK_FILE)
    with DirectoryLock(out):
        assert not os.path.samefile(out / LOCK_FILE, victim)
        assert (out / LOCK_FILE).read_text().strip() == str(os.getpid())
    assert victim.read_bytes() == b"precious\n"


@pytest.mark.slow
def test_probe_selection_layer_extension_checked_before_rendering(gallery, tmp_path):
    """A --selection-layer phrt cannot write (not .usda / .usdc / .usd) is refused with
    exit 2 before the first frame renders: no image, no stats."""
    out = tmp_path / "out"
    done = _cli("render", str(gallery), "--out", str(out), "--frames", "1:2", "--budget-rays",
                "600", "--resolution", "32x24",
                "--selection-layer", str(out / "layer.txt"))  # fmt: skip
    assert "extension must be" in _one_line_error(done, 2)
    assert not (out / "frames").exists() and not (out / "stats.json").exists()


# --- failures mid-run ---------------------------------------------------------------------


@pytest.mark.slow
def test_a_failing_frame_keeps_the_finished_frames_records(gallery, tmp_path, monkeypatch):
    from phrt_usd.run import render_job

    real = render_job.render_frame
    calls = []

    def failing(renderer, t, *files):
        calls.append(t)
        if len(calls) == 3:
            raise PhrtError(f"frame {t}: injected failure")
        return real(renderer, t, *files)

    monkeypatch.setattr(render_job, "render_frame", failing)
    out = tmp_path / "out"
    with pytest.raises(PhrtError, match="injected"):
        run_render(RenderJob(stage_path=gallery, out_dir=out, options=OPTIONS, frames="1:4"))
    stats = json.loads((out / "stats.json").read_text())
    assert [f["time"] for f in stats["frames"]] == [1.0, 2.0]
    checkpoint = json.loads((out / CHECKPOINT_FILE).read_text())
    assert len(checkpoint["frames"]) == 2
    monkeypatch.setattr(render_job, "render_frame", real)
    run_render(RenderJob(stage_path=gallery, out_dir=out, options=OPTIONS, frames="1:4",
                         resume=True))  # fmt: skip
    stats = json.loads((out / "stats.json").read_text())
    assert [f["time"] for f in stats["frames"]] == [1.0, 2.0, 3.0, 4.0]


@pytest.fixture
def small_disk(tmp_path):
    """A 300 KiB tmpfs (as root), else None: room for a few 160x120 frames (~20 KiB
    each) beside the run's 64 KiB disk reserve, not 30."""
    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0:
        yield None
        return
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=300k", "tmpfs", str(mount)],
                          capture_output=True)  # fmt: skip
    if done.returncode != 0:
        yield None
        return
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


@pytest.mark.slow
def test_full_disk_leaves_no_broken_file_and_keeps_records(
    gallery, tmp_path, small_disk, monkeypatch, check_readable
):
    """On a full disk the render ends with one line naming the file and the OS error; no
    file under a final name is broken and the finished frames are in stats.json."""
    options = RenderOptions(width=160, height=120, budget_ms=None, budget_rays=600)
    stage = mirror_gallery_stage(tmp_path / "g.usda", frames=30)
    if small_disk is None:  # not root or no tmpfs: inject ENOSPC into the image writer
        from phrt_usd.run import images

        real, calls = images._write, []

        def full(path, spec, pixels):
            calls.append(path)
            if len(calls) > 7:
                raise OSError(28, "No space left on device", str(path))
            real(path, spec, pixels)

        monkeypatch.setattr(images, "_write", full)
        out = tmp_path / "out"
    else:
        out = small_disk / "out"
    job = RenderJob(stage_path=stage, out_dir=out, options=options, frames="1:30")
    with pytest.raises(WriteFailed, match="(?i)no space left on device"):
        run_render(job)
    assert check_readable(out) > 0
    assert not [p for p in out.rglob(".*") if p.name != LOCK_FILE]  # no temp left
    stats = json.loads((out / "stats.json").read_text())
    finished = [f["time"] for f in stats["frames"]]
    assert 0 < len(finished) < 30
    for t in finished:
        assert (out / "frames" / f"{int(t):04d}.exr").stat().st_size > 0
        assert (out / "frames" / f"{int(t):04d}.png").stat().st_size > 0


@pytest.mark.slow
def test_kill_9_never_leaves_an_unreadable_final_file(tmp_path, check_readable):
    """SIGKILL at random moments of a render: every file under its final name reads (temp
    files may remain; they are hidden and never mistaken for output)."""
    stage = mirror_gallery_stage(tmp_path / "g.usda", frames=60)
    rng = random.Random(7)
    checked = 0
    for trial in range(4):
        out = tmp_path / f"out{trial}"
        proc = subprocess.Popen([*CLI, "render", str(stage), "--out", str(out), "--frames",
                                 "1:60", "--budget-rays", "600", "--resolution", "64x48"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        deadline = time.monotonic() + 120
        while not (out / "frames").exists() and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 1.5))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        checked += check_readable(out)
        # The killed run's lock died with it: --resume continues.
        done = _cli("render", str(stage), "--out", str(out), "--frames", "1:60",
                    "--budget-rays", "600", "--resolution", "64x48", "--resume")  # fmt: skip
        assert done.returncode == 0, done.stderr
    assert checked > 0


# --- bounds and exit codes ----------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    "args",
    [
        ["--budget-rays", str(10**30)],
        ["--budget-rays", "-1"],
        ["--resolution", "100000x10"],
        ["--resolution", "10000x10000"],
        ["--resolution", "axb"],
        ["--frames", "1:100000000"],
        ["--frames", "1:9x0"],
        ["--frames", "5:1:1"],
        ["--mode", "fast"],
        ["--budget-ms", "nan"],
    ],
)
def test_bad_option_values_exit_2_with_one_line(gallery, tmp_path, args):
    done = _cli("render", str(gallery), "--out", str(tmp_path / "o"), *args)
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    assert not (tmp_path / "o" / "stats.json").exists()


@pytest.mark.slow
def test_os_conditions_are_one_line(gallery, tmp_path):
    as_file = tmp_path / "file"
    as_file.write_text("x")
    _one_line_error(_cli("render", str(gallery), "--out", str(as_file), "--frames", "1"), 2)
    _one_line_error(_cli("render", str(gallery), "--out", str(as_file / "sub"),
                         "--frames", "1"), 2)  # fmt: skip
    no_ext = tmp_path / "stage_without_extension"
    no_ext.write_bytes(gallery.read_bytes())
    _one_line_error(_cli("render", str(no_ext), "--out", str(tmp_path / "o")), 2)
    done = _cli("render", str(gallery), "--out", str(as_file), "--json")
    assert done.returncode == 2
    error = json.loads(done.stdout)
    assert error["code"] == 2 and "not a directory" in error["error"]


@pytest.mark.slow
def test_read_only_out_is_one_line(gallery, tmp_path):
    if os.geteuid() != 0:
        pytest.skip("needs root to mount a read-only tmpfs")
    mount = tmp_path / "ro"
    mount.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(mount)],
                      capture_output=True).returncode != 0:  # fmt: skip
        pytest.skip("no tmpfs here")
    try:
        line = _one_line_error(_cli("render", str(gallery), "--out", str(mount / "o"),
                                    "--frames", "1"), 2)  # fmt: skip
        assert "Read-only file system" in line
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


@pytest.mark.slow
def test_a_second_sweep_into_a_locked_out_is_refused(tmp_path):
    """Sweeps hold OUT's lock too: a sweep (or render) into a busy OUT is refused at once,
    naming the holder's pid."""
    stage = mirror_gallery_stage(tmp_path / "g.usda", frames=2)
    out = tmp_path / "sweep"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from pathlib import Path; "
        "from phrt_usd.run.run_directory import DirectoryLock; "
        f"lock = DirectoryLock(Path({str(out)!r})).acquire(); print('held', flush=True); "
        "time.sleep(60)")], stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        done = _cli("sweep", str(stage), "--out", str(out), "--frames", "1:1",
                    "--resolution", "32x24", "--budgets-rays", "100")  # fmt: skip
        assert f"pid {holder.pid}" in _one_line_error(done, 1)
    finally:
        holder.kill()
        holder.wait()
    with DirectoryLock(out):  # the kernel released the killed holder's lock
        pass
