"""sweep_report: summary.md agrees with sweep.csv, plots are valid PNGs, report.html is
self-contained (every referenced file exists, no external URL, no script, text escaped).

The sweep directory is synthetic (``synthetic_sweep.py``; the ``report_dir`` fixture of
this folder's conftest writes it with its report, as for the browser test).
"""

from __future__ import annotations

import csv
import html
import json
import math
import statistics
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np
import OpenImageIO as oiio
import pytest
from synthetic_sweep import COLUMNS, FRAMES, IMAGE_FRAME, STAGES, write_synthetic_sweep

from phrt_usd.errors import PhrtError
from phrt_usd.evaluate.sweep_plots import timeline_states
from phrt_usd.evaluate.sweep_report import write_sweep_report
from phrt_usd.evaluate.sweep_summary import PAPER_FIGURES, summarize
from phrt_usd.evaluate.sweep_tables import equal_time_comparison, frontier_flip_at

#: synthetic_sweep.CONFIGS in the order the report shows them.
EXPECTED_ORDER = [
    "raster", "heu1@4ms", "heu2@4ms", "heu1@8ms", "heu2@8ms", "heu1@20000rays", "heu1@inf",
    "all", "rt",
]  # fmt: skip


# --- reading the outputs back -----------------------------------------------------------


def parse_summary_md(text: str) -> dict[str, list[dict[str, str]]]:
    """{stage: [row dict by header]} from summary.md's tables: a stage's tables (each
    starting with the config column, rows in the same order) joined row by row."""
    tables: dict[str, list[dict[str, str]]] = {}
    stage, header, row_index = None, None, 0
    for line in text.splitlines():
        if line.startswith("## "):
            stage = line.removeprefix("## Stage ").strip() if line.startswith("## Stage ") else None
            header = None
            if stage is not None:
                tables[stage] = []
        elif not line.startswith("|"):
            header = None  # a table ends at the first line that is not a row
        elif stage is not None:
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if header is None:
                header, row_index = cells, 0
            elif not set("".join(cells)) <= set("-:"):
                row = dict(zip(header, cells, strict=True))
                rows = tables[stage]
                if row_index < len(rows):
                    assert rows[row_index]["config"] == row["config"], "tables' rows disagree"
                    rows[row_index].update(row)
                else:
                    rows.append(row)
                row_index += 1
    return tables


def expected_from_csv(
    path: Path, timeline_path: Path | None = None
) -> dict[tuple[str, str], dict[str, float | None]]:
    """Independent recomputation of the summary's figures straight from the CSV.

    Chances to switch come from timeline.json (reflector visible in consecutive frames)
    if given, else from the CSV's visible counts after the first frame.
    """
    timeline = json.loads(timeline_path.read_text()) if timeline_path else None
    groups: dict[tuple[str, str], list[dict[str, str]]] = {}
    with path.open(newline="") as handle:
        for row in csv.DictReader(handle):
            groups.setdefault((row["stage"], row["config"]), []).append(row)

    def mean(rows, column):
        values = [float(r[column]) for r in rows if r[column] != ""]
        return sum(values) / len(values) if values else None

    def quantile(rows, column, which):
        """5th / 50th / 95th percentile, linear between order statistics (``inclusive``)."""
        values = sorted(float(r[column]) for r in rows if r[column] != "")
        if len(values) < 2:
            return values[0] if values else None
        return statistics.quantiles(values, n=20, method="inclusive")[which // 5 - 1]

    def within(rows):
        """Share of frames within the budget: trace ms <= 1.1 T, or rays <= the rays budget."""
        budget_ms, budget_rays = rows[0]["budget_ms"], rows[0]["budget_rays"]
        if budget_ms not in ("", "inf"):
            return sum(float(r["trace_ms"]) <= 1.1 * float(budget_ms) for r in rows) / len(rows)
        if budget_rays not in ("", "inf"):
            return sum(float(r["rays"]) <= float(budget_rays) for r in rows) / len(rows)
        return None

    expected = {}
    for key, rows in groups.items():
        rows.sort(key=lambda r: float(r["frame"]))
        frame_ms = [float(r["frame_ms"]) for r in rows]
        transitions = sum(int(r["transitions"]) for r in rows)
        steps = sum(int(r["density_steps"]) for r in rows)
        if timeline is None:
            chances = sum(int(r["visible"]) for r in rows[1:])
        else:
            visible = timeline[key[0]][key[1]]["visible"]
            chances = sum(
                1
                for f in range(1, len(visible))
                for i in range(len(visible[f]))
                if visible[f][i] and visible[f - 1][i]
            )
        expected[key] = {
            "frames": len(rows),
            "mean frame ms": statistics.fmean(frame_ms),
            "median frame ms": statistics.median(frame_ms),
            "p5 frame ms": quantile(rows, "frame_ms", 5),
            "p95 frame ms": quantile(rows, "frame_ms", 95),
            "mean fps": 1000.0 / statistics.fmean(frame_ms),
            "mean trace ms": mean(rows, "trace_ms"),
            "p95 trace ms": quantile(rows, "trace_ms", 95),
            "within budget": within(rows),
            "mean FLIP": mean(rows, "flip"),
            "median FLIP": quantile(rows, "flip", 50),
            "p5 FLIP": quantile(rows, "flip", 5),
            "p95 FLIP": quantile(rows, "flip", 95),
            "mean FLIP reflectors": mean(rows, "flip_reflectors"),
            "mean PSNR dB": mean(rows, "psnr"),
            "transitions": transitions,
            "transition rate": 100.0 * transitions / chances if chances else None,
            "density steps": steps,
            "mean selected": mean(rows, "selected"),
            "mean temporal error": mean(rows, "temporal_error"),
            "median temporal error": quantile(rows, "temporal_error", 50),
            "p5 temporal error": quantile(rows, "temporal_error", 5),
            "p95 temporal error": quantile(rows, "temporal_error", 95),
            "mean temporal error reflectors": mean(rows, "temporal_error_reflectors"),
        }
    return expected


def assert_printed_close(text: str, value: float, what: str) -> None:
    """``text`` is ``value`` rounded as printed: fixed decimals or 3 significant digits."""
    number = text.strip().removesuffix("%").strip()
    printed = float(number)
    mantissa = number.lstrip("-").split("e")[0]
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    exponent = int(number.split("e")[1]) if "e" in number else 0
    half_step = 0.5 * 10.0 ** (exponent - decimals)
    assert abs(printed - value) <= half_step * 1.0001 + 1e-12, f"{what}: {text} vs {value}"
    if printed != 0.0 and value > 1e-3 and ("FLIP" in what or "temporal" in what):
        # FLIP and temporal-error columns carry 3 significant digits.
        assert abs(printed - value) / value < 5e-3, f"{what}: {text} vs {value}"


class _Refs(HTMLParser):
    def __init__(self):
        super().__init__()
        self.refs, self.tags, self.img_count = [], [], 0

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.img_count += tag == "img"
        for name, value in attrs:
            if name in ("src", "href") and value is not None:
                self.refs.append(value)


# --- tests ------------------------------------------------------------------------------


@pytest.mark.slow
def test_summary_md_agrees_with_csv(report_dir):
    text = (report_dir / "summary.md").read_text()
    tables = parse_summary_md(text)
    expected = expected_from_csv(report_dir / "sweep.csv", report_dir / "timeline.json")
    assert "approximated" not in text  # every config's chances came from the timeline
    assert list(tables) == list(STAGES)
    for stage, table in tables.items():
        assert [row["config"] for row in table] == EXPECTED_ORDER
        for row in table:
            want = expected[(stage, row["config"])]
            for column, value in want.items():
                cell = row[column]
                if column == "within budget":
                    # One decimal of a percentage: half a step is 0.05 %.
                    shown = "n/a" if value is None else f"{100.0 * value:.1f} %"
                    assert cell == shown, (stage, row["config"], column)
                elif value is None:
                    assert cell == "—", (stage, row["config"], column)
                elif column in ("frames", "transitions", "density steps"):
                    assert int(cell) == value, (stage, row["config"], column)
                else:
                    assert_printed_close(cell, value, f"{stage} {row['config']} {column}")


@pytest.mark.slow
def test_summary_budgets_and_paper_line(report_dir):
    text = (report_dir / "summary.md").read_text()
    table = parse_summary_md(text)["farm"]
    budgets = {row["config"]: row["budget"] for row in table}
    assert budgets["heu1@4ms"] == "4 ms"
    assert budgets["heu1@20000rays"] == "20000 rays"
    assert budgets["heu1@inf"] == "unbounded"
    assert budgets["raster"] == "—"
    # Without paper.json the defaults from docs/design.md §1 are shown, once per stage.
    assert text.count("fps HEU1 25.4 / HEU2 26.4") == 1
    assert text.count("fps HEU1 21.8 / HEU2 23.3") == 1
    assert "transitions HEU1/HEU2 3.8 %" in text
    # Ours: at 4 ms and 8 ms both heuristics ran; the ratio is HEU1 / HEU2 transitions.
    expected = expected_from_csv(report_dir / "sweep.csv")
    t1, t2 = (
        expected[("farm", "heu1@4ms")]["transitions"],
        expected[("farm", "heu2@4ms")]["transitions"],
    )
    assert f"({t1} / {t2})" in text
    assert text.count("This sweep at budget") == 2 * len(STAGES)


@pytest.mark.slow
def test_without_timeline_rate_is_approximated_from_csv(tmp_path):
    out = write_synthetic_sweep(tmp_path / "sweep", seed=5)
    (out / "timeline.json").unlink()
    write_sweep_report(out)
    text = (out / "summary.md").read_text()
    expected = expected_from_csv(out / "sweep.csv")
    for stage, table in parse_summary_md(text).items():
        for row in table:
            value = expected[(stage, row["config"])]["transition rate"]
            assert_printed_close(row["transition rate"], value, f"{stage} {row['config']}")
    assert text.count("Transition rate approximated") == len(STAGES)
    assert not list(out.glob("timeline_*.png"))
    assert "timeline_" not in (out / "report.html").read_text()


@pytest.mark.slow
def test_paper_json_overrides_defaults(tmp_path):
    out = write_synthetic_sweep(tmp_path / "sweep", seed=3)
    paper = {"farm": {"heu1_fps": 11.5, "heu2_fps": 12.5, "transitions_ratio": 0.5,
                      "heu1_selected": 2, "heu2_selected": 3}}  # fmt: skip
    (out / "paper.json").write_text(json.dumps(paper))
    write_sweep_report(out)
    text = (out / "summary.md").read_text()
    assert "fps HEU1 11.5 / HEU2 12.5" in text
    assert "transitions HEU1/HEU2 50.0 %" in text
    assert "25.4" not in text
    assert "no figures for stage 'sewer'" in text


@pytest.mark.slow
def test_plots_are_small_valid_pngs(report_dir):
    for name in ("error_vs_time.png", "error_vs_time_farm.png", "error_vs_time_sewer.png"):
        path = report_dir / name
        assert path.stat().st_size < 150_000, name
        image = oiio.ImageInput.open(str(path))
        assert image is not None, oiio.geterror()
        spec = image.spec()
        pixels = image.read_image(oiio.UINT8)
        image.close()
        assert (spec.width, spec.height) == (900, 1000), name  # three panels
        assert pixels.std() > 5.0, f"{name} looks blank"
    for stage in STAGES:
        image = oiio.ImageInput.open(str(report_dir / f"timeline_{stage}.png"))
        assert image is not None
        pixels = image.read_image(oiio.UINT8)
        image.close()
        # The traced colour (#d62728) must appear: some reflectors are traced.
        red = (pixels[..., 0] == 0xD6) & (pixels[..., 1] == 0x27) & (pixels[..., 2] == 0x28)
        assert red.any(), stage


@pytest.mark.slow
def test_report_html_references_only_existing_local_files(report_dir):
    text = (report_dir / "report.html").read_text()
    parser = _Refs()
    parser.feed(text)
    assert "script" not in parser.tags and "link" not in parser.tags
    assert parser.refs, "report references no images"
    for ref in parser.refs:
        parts = urlsplit(ref)
        assert not parts.scheme and not parts.netloc, f"external reference {ref}"
        assert not ref.startswith("/"), f"absolute path {ref}"
        assert (report_dir / unquote(parts.path)).is_file(), f"missing {ref}"
    refs = {unquote(r) for r in parser.refs}
    assert "error_vs_time.png" in refs
    for stage in STAGES:
        assert f"timeline_{stage}.png" in refs
        for name in ("all", "raster", "heu1@4ms", "heu1@4ms_flip", "rt_flip"):
            assert f"images/{stage}/{IMAGE_FRAME}/{name}.png" in refs
    for config in EXPECTED_ORDER:
        assert f"<td>{config}</td>" in text
    # The data behind the tables, linked relatively (their existence is checked above).
    assert {"sweep.csv", "summary.csv", "timeline.json", "summary.md"} <= refs


@pytest.mark.slow
def test_text_is_escaped_in_html_and_markdown(tmp_path):
    evil = "<script>alert(1)</script>|x&y"
    configs = [("all", "all", "hybrid", "", ""), (evil, "heu1", "hybrid", "4", "")]
    out = write_synthetic_sweep(tmp_path / "sweep", configs=configs)
    write_sweep_report(out)
    html_text = (out / "report.html").read_text()
    assert "<script" not in html_text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;|x&amp;y" in html_text
    table = parse_summary_md((out / "summary.md").read_text().replace("\\|", "¦"))["farm"]
    assert [row["config"] for row in table] == [evil.replace("|", "¦"), "all"]


def test_timeline_states():
    selected = np.array([[True, False, False], [True, True, False]])
    visible = np.array([[True, True, False], [False, True, False]])
    states = timeline_states(selected, visible)
    assert states.shape == (3, 2)  # reflectors x frames
    assert states.tolist() == [[2, 3], [1, 2], [0, 0]]


def _rows(**overrides):
    row = {c: "1" for c in COLUMNS} | {"stage": "farm", "config": "heu1@4ms",
                                       "heuristic": "heu1", "mode": "hybrid",
                                       "budget_ms": "4", "budget_rays": ""}  # fmt: skip
    return [row | overrides]


def test_bad_inputs_raise_one_line_errors(tmp_path):
    with pytest.raises(PhrtError, match="flip.*not a finite number"):
        summarize(_rows(flip="abc"))
    with pytest.raises(PhrtError, match="frame_ms"):
        summarize(_rows(frame_ms="nan"))
    varying = _rows() + _rows(frame="2", budget_ms="8")
    with pytest.raises(PhrtError, match="budget_ms varies"):
        summarize(varying)
    with pytest.raises(PhrtError, match="not found"):
        write_sweep_report(tmp_path / "nothing")
    out = write_synthetic_sweep(tmp_path / "short")
    rows = (out / "sweep.csv").read_text().splitlines()
    (out / "sweep.csv").write_text(rows[0].replace(",flip,", ",flop,") + "\n" + rows[1] + "\n")
    with pytest.raises(PhrtError, match="missing column.*flip"):
        write_sweep_report(out)
    out = write_synthetic_sweep(tmp_path / "badtimeline")
    timeline = json.loads((out / "timeline.json").read_text())
    timeline["farm"]["rt"]["selected"].pop()
    (out / "timeline.json").write_text(json.dumps(timeline))
    with pytest.raises(PhrtError, match="'farm' config 'rt': selected"):
        write_sweep_report(out)


def test_unbounded_and_missing_values_stay_finite():
    rows = _rows(budget_ms="inf", temporal_error="", temporal_error_reflectors="", frame_ms="0")
    (entry,) = summarize(rows)
    assert entry["budget"] == "unbounded"
    assert entry["mean_fps"] is None  # 0 ms mean frame time: no infinite fps
    assert entry["mean_temporal_error"] is None
    assert entry["transition_rate"] is None  # a single frame has no chance to switch
    assert all(
        not (isinstance(v, float) and not math.isfinite(v))
        for k, v in entry.items()
        if k not in ("budget_ms", "budget_rays")
    )


def test_paper_defaults_match_design():
    assert PAPER_FIGURES["farm"]["heu1_fps"] == 25.4
    assert PAPER_FIGURES["sewer"]["transitions_ratio"] == 0.046


def test_frontier_interpolates_the_best_error_within_a_time():
    points = [(50.0, 0.05), (52.0, 0.03), (51.0, 0.06), (54.0, 0.01)]  # (51, 0.06) dominated
    assert frontier_flip_at(points, 49.0) is None  # faster than any point
    assert frontier_flip_at(points, 50.0) == pytest.approx(0.05)
    assert frontier_flip_at(points, 51.0) == pytest.approx(0.04)
    assert frontier_flip_at(points, 53.0) == pytest.approx(0.02)
    assert frontier_flip_at(points, 99.0) == pytest.approx(0.01)  # held beyond the slowest
    assert frontier_flip_at([(50.0, 0.05), (50.0, 0.04)], 50.0) == pytest.approx(0.04)


def test_equal_time_comparison_counts_where_heu1_is_not_worse():
    def entry(h, ms_budget, frame_ms, flip):
        return {
            "stage": "s", "heuristic": h, "budget_ms": ms_budget, "budget_rays": None,
            "budget": f"{ms_budget} ms", "mean_frame_ms": frame_ms, "mean_flip": flip,
        }  # fmt: skip

    summary = [
        entry("heu2", 0.0, 50.0, 0.05), entry("heu2", 4.0, 52.0, 0.03),
        entry("heu2", None, 54.0, 0.0),  # unbounded: no budget of either kind
        entry("heu1", 0.0, 50.0, 0.05), entry("heu1", 2.0, 51.0, 0.039),  # HEU2 there: 0.04
        entry("heu1", 4.0, 53.0, 0.016),  # HEU2 there: 0.015
        entry("heu1", None, 54.0, 0.0),
    ]  # fmt: skip
    (line,) = equal_time_comparison(summary, "s")  # no rays axis for ms budgets
    assert "ms budgets" in line and "at 1 of 2" in line
    assert "2.0 ms: 0.039 at 51.00 ms vs HEU2 0.04" in line
    assert "4.0 ms: 0.016 at 53.00 ms vs HEU2 0.015" in line


def test_equal_rays_comparison_for_rays_budgets():
    def entry(h, rays_budget, frame_ms, rays, flip):
        return {
            "stage": "s", "heuristic": h, "budget_ms": None, "budget_rays": rays_budget,
            "budget": f"{rays_budget} rays", "mean_frame_ms": frame_ms, "mean_rays": rays,
            "mean_flip": flip,
        }  # fmt: skip

    summary = [
        entry("heu2", 0.0, 50.0, 0.0, 0.05), entry("heu2", 1000.0, 52.0, 600.0, 0.03),
        entry("heu2", None, 54.0, 2000.0, 0.0),
        # Fewer rays than HEU2 at the same budget, slower (selection overhead): worse at
        # equal frame time, better at equal rays (HEU2 at 300 rays: 0.04).
        entry("heu1", 1000.0, 53.0, 300.0, 0.035),
        entry("heu1", None, 54.0, 2000.0, 0.0),
    ]  # fmt: skip
    time_line, rays_line = equal_time_comparison(summary, "s")
    assert time_line.startswith("Equal mean frame time (rays budgets") and "at 0 of 1" in time_line
    assert rays_line.startswith("Equal mean traced rays (rays budgets") and "at 1 of 1" in rays_line
    assert "1000.0 rays: 0.035 at 300 rays vs HEU2 0.04" in rays_line


@pytest.mark.slow
def test_summary_csv_and_pareto_marks_agree_with_the_tables(report_dir):
    """summary.csv carries the temporal error unrounded (recomputed from sweep.csv) and
    the same Pareto marks as summary.md; every stage has a front, and within a stage no
    marked config is beaten on all of (frame ms, FLIP, temporal error) by another."""
    expected = expected_from_csv(report_dir / "sweep.csv", report_dir / "timeline.json")
    with (report_dir / "summary.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == len(expected)
    tables = parse_summary_md((report_dir / "summary.md").read_text())
    marks = {(s, r["config"]): r["Pareto"] == "◆" for s, t in tables.items() for r in t}
    for row in rows:
        key = (row["stage"], row["config"])
        assert float(row["mean_temporal_error"]) == pytest.approx(
            expected[key]["mean temporal error"], rel=1e-12
        )
        assert (row["pareto"] == "1") == marks[key], key
    for stage in STAGES:
        points = [
            (float(r["mean_frame_ms"]), float(r["mean_flip"]), float(r["mean_temporal_error"]))
            for r in rows
            if r["stage"] == stage
        ]
        front = [p for p, r in zip(points, [r for r in rows if r["stage"] == stage],
                                   strict=True) if r["pareto"] == "1"]  # fmt: skip
        assert front
        for p in front:
            assert not any(all(q[i] <= p[i] for i in range(3)) and q != p for q in points)


@pytest.mark.slow
def test_budget_adherence_names_the_configs_that_miss_their_budget(tmp_path):
    """HEU1 and HEU2 at 2 ms whose trace phase averages 3.06 and 3.47 ms: the table gives
    each one's share of frames within T + 10 % (2.2 ms) and the notes of summary.md and
    report.html name both as not holding the budget, with their mean trace time; a config
    within it in every frame is named as holding it; configs without a budget say n/a."""
    configs = [
        ("all", "all", "hybrid", "", ""), ("heu1@2ms", "heu1", "hybrid", "2", ""),
        ("heu2@2ms", "heu2", "hybrid", "2", ""), ("heu1@8ms", "heu1", "hybrid", "8", ""),
    ]  # fmt: skip
    out = write_synthetic_sweep(tmp_path / "sweep", configs=configs)
    # Per frame trace ms: one frame of six within 2.2 ms for HEU1, none for HEU2.
    trace = {
        "heu1@2ms": [2.0, 3.0, 3.2, 3.3, 3.4, 3.46],  # mean 3.06
        "heu2@2ms": [3.3, 3.4, 3.5, 3.5, 3.6, 3.52],  # mean 3.47
        "heu1@8ms": [1.0, 2.0, 3.0, 4.0, 5.0, 8.8],  # the last exactly at T + 10 %
    }
    rows = list(csv.DictReader((out / "sweep.csv").open(newline="")))
    for row in rows:
        if row["config"] in trace:
            row["trace_ms"] = trace[row["config"]][FRAMES.index(float(row["frame"]))]
    with (out / "sweep.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    write_sweep_report(out)
    text = (out / "summary.md").read_text()
    table = {row["config"]: row for row in parse_summary_md(text)["farm"]}
    assert table["heu1@2ms"]["within budget"] == "16.7 %"  # 1 of 6 frames
    assert table["heu2@2ms"]["within budget"] == "0.0 %"
    assert table["heu1@8ms"]["within budget"] == "100.0 %"
    assert table["all"]["within budget"] == "n/a"
    assert table["heu1@2ms"]["mean trace ms"] == "3.06"
    assert table["heu2@2ms"]["mean trace ms"] == "3.47"
    html_text = (out / "report.html").read_text()
    for page in (text, html_text):
        missed = next(line for line in page.splitlines() if "Time budget NOT held" in line)
        assert "heu1@2ms within 2.2 ms in 16.7 % of frames (mean trace 3.06 ms" in missed
        assert "heu2@2ms within 2.2 ms in 0.0 % of frames (mean trace 3.47 ms" in missed
        assert "heu1@8ms" not in missed
        held = next(line for line in page.splitlines() if "Time budget held" in line)
        assert "heu1@8ms (100.0 %)" in held


@pytest.mark.slow
def test_summary_and_report_show_the_provenance(tmp_path):
    """With provenance.json the summary and the page list its items; without (a sweep
    directory of an older phrt) they say it was not recorded."""
    from phrt_usd.evaluate.provenance import collect, provenance_items

    out = write_synthetic_sweep(tmp_path / "sweep")
    write_sweep_report(out)
    for name in ("summary.md", "report.html"):
        assert "not recorded (this sweep directory has no provenance.json)" in (
            out / name
        ).read_text()
    record = collect(threads=3, gl="osmesa", argv=["phrt", "sweep", "farm.usda"])
    (out / "provenance.json").write_text(json.dumps(record))
    write_sweep_report(out)
    text, html_text = (out / "summary.md").read_text(), (out / "report.html").read_text()
    for label, value in provenance_items(record):
        assert f"- {label}: {value}" in text
        assert f"<dt>{label}</dt><dd>{html.escape(value)}</dd>" in html_text
    assert "threads: 3" in text and "phrt sweep farm.usda" in text
