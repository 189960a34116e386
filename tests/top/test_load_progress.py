"""The load's progress: ``progress.step`` reaches only a listener, the ``LoadLine`` shows
nothing for a load under a second and one line (rewritten on a terminal, plain lines in
a log) past it, and ``phrt render`` shows it unless ``-q`` or ``--json``."""

from __future__ import annotations

import io

import pytest
from scenes import clean_stage
from typer.testing import CliRunner

from phrt_usd import load_line, progress
from phrt_usd.cli import app
from phrt_usd.load_line import LoadLine


class _Clock:
    """Seconds that pass when the test says so."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_step_reaches_a_listener_only_inside_its_block():
    heard = []
    progress.step("nobody listens")  # no listener: nothing happens, nothing fails
    with progress.listening(lambda *args: heard.append(args)):
        progress.step("reading prims", 3)
        progress.step("triangulating", 10, 40)
    progress.step("after the block")
    assert heard == [("reading prims", 3, None), ("triangulating", 10, 40)]


def _line(tty: bool, enabled: bool = True):
    clock, stream = _Clock(), io.StringIO()
    return LoadLine("big.usd", enabled=enabled, stream=stream, tty=tty, clock=clock), clock, stream


@pytest.mark.parametrize("tty", [False, True])
def test_a_load_under_a_second_shows_nothing(tty):
    line, clock, stream = _line(tty)
    with line:
        progress.step("reading prims", 10)
        clock.now += 0.9  # under SHOW_AFTER_SECONDS
        progress.step("building the BVH")
    assert stream.getvalue() == ""


def test_a_slow_load_rewrites_one_terminal_line_and_ends_it():
    line, clock, stream = _line(tty=True)
    with line:
        progress.step("reading prims", 10)
        clock.now += 1.5
        progress.step("reading prims", 20)
        clock.now += 0.01  # under REDRAW_SECONDS: the same step is not drawn again
        progress.step("reading prims", 30)
        clock.now += 0.5
        progress.step("building the BVH of 1,430,784 triangles")
        clock.now += 2.0
    out = stream.getvalue()
    assert "\n" not in out[:-1]  # one line, rewritten in place until it ends
    draws = out.split("\r")[1:]
    assert draws == [
        "load big.usd: reading prims 20 (2 s)\x1b[K",
        "load big.usd: building the BVH of 1,430,784 triangles (2 s)\x1b[K",
        "load big.usd: ready in 4.0 s\x1b[K\n",
    ]


def test_off_a_terminal_a_slow_load_prints_a_line_per_step():
    line, clock, stream = _line(tty=False)
    with line:
        clock.now += 1.2
        progress.step("triangulating", 262144, 1430784)
        clock.now += 1.0  # the same step within LOG_LINE_SECONDS: not printed again
        progress.step("triangulating", 524288, 1430784)
        progress.step("placing elements", 20, 49)
    assert stream.getvalue().splitlines() == [
        "load big.usd: triangulating 262,144/1,430,784 (1 s)",
        "load big.usd: placing elements 20/49 (2 s)",
        "load big.usd: ready in 2.2 s",
    ]


def test_a_failed_load_erases_its_line_and_says_no_ready():
    line, clock, stream = _line(tty=True)
    with pytest.raises(RuntimeError), line:
        clock.now += 2.0
        progress.step("reading prims", 5)
        raise RuntimeError("bad mesh")
    assert stream.getvalue().endswith("\r\x1b[K") and "ready" not in stream.getvalue()


@pytest.mark.parametrize("tty", [False, True])
def test_a_disabled_line_prints_nothing(tty):
    line, clock, stream = _line(tty, enabled=False)
    with line:
        clock.now += 5.0
        progress.step("reading prims", 10)
    assert stream.getvalue() == ""


@pytest.mark.slow
@pytest.mark.parametrize("flags", [(), ("-q",), ("--json",)])
def test_render_shows_the_load_line_unless_quiet_or_json(tmp_path, monkeypatch, flags):
    """Every load is slow once the threshold is 0 s: ``phrt render`` then prints the
    load's lines on stderr (not a terminal here: plain lines), ending in ``ready``;
    with ``-q`` or ``--json`` none."""
    stage = clean_stage(tmp_path / "good.usda")
    stage.GetRootLayer().Save()
    monkeypatch.setattr(load_line, "SHOW_AFTER_SECONDS", 0.0)
    quiet = [f for f in flags if f == "-q"]
    args = [*quiet, "render", str(tmp_path / "good.usda"), "--out", str(tmp_path / "run"),
            "--frames", "1", "--resolution", "32x24", *[f for f in flags if f != "-q"]]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    lines = [s for s in result.stderr.splitlines() if s.startswith("load good.usda: ")]
    if flags:
        assert lines == [], result.stderr
    else:
        assert any("reading prims" in s for s in lines), result.stderr
        assert lines[-1].startswith("load good.usda: ready in "), result.stderr
