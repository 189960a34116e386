"""The render options declared once (phrt_usd.model.render_options.OPTIONS) and the one
set of value checks (phrt_usd.checks): the schema's fallbacks, the CLI's help and
defaults, SweepSpec and docs/api.md read the table; every option's bad value is one
line through the checks; set-up and frame options are apart."""

from __future__ import annotations

import math
import re
from dataclasses import fields

import numpy as np
import pytest
import typer
from pxr import Usd
from repo_paths import DOCS

import phrt_usd  # noqa: F401  (registers the Phrt schemas)
from phrt_usd.checks import (
    check_bool,
    check_choice,
    check_finite,
    check_integer,
    check_number,
    check_range,
    check_token,
)
from phrt_usd.cli import app
from phrt_usd.errors import BadOption
from phrt_usd.evaluate.sweep import SweepSpec
from phrt_usd.model.render_options import (
    FRAME,
    OPTIONS,
    SETUP,
    FrameOptions,
    RenderOptions,
    SetupOptions,
)
from phrt_usd.usd import schema

DOCS_API = DOCS / "api.md"
#: Options given together as --resolution / resolution= (one row, one CLI option).
SIZE = ("width", "height")


def _docs_rows() -> dict[str, list[str]]:
    """docs/api.md's option table: option name -> its cells (``\\|`` is a cell's bar)."""
    rows = {}
    for line in DOCS_API.read_text().splitlines():
        if line.startswith("| `"):
            cells = [c.strip() for c in re.split(r"(?<!\\)\|", line.strip().strip("|"))]
            rows[cells[0].strip("`")] = cells
    return rows


def test_probe_options_declared_in_many_places_docs_table():
    """docs/api.md states every render option's values and default as OPTIONS declares
    them, and names its CLI option first (bounce_limit's 0..5 and the missing heu3 and
    target_fps were such drift)."""
    rows = _docs_rows()
    for name, option in OPTIONS.items():
        if name in SIZE:
            continue
        assert name in rows, f"docs/api.md has no row for {name}"
        _, values, default, meaning = rows[name]
        assert values == option.doc_values(), name
        assert default == option.doc_default(), name
        assert meaning.startswith(f"`{option.cli}`"), name
    width, height = OPTIONS["width"].default, OPTIONS["height"].default
    assert rows["resolution"][2] == f"`({width}, {height})`"


def test_probe_options_declared_in_many_places_schema_fallbacks():
    """The schema's fallbacks and allowed tokens (generatedSchema.usda, what a stage reads
    without an opinion) are the table's defaults and choices, and usd.schema's names are
    the table's."""
    definition = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(schema.RENDER_SETTINGS_API)
    declared = [o for o in OPTIONS.values() if o.schema_attribute]
    assert {o.schema_attribute for o in declared} == set(definition.GetPropertyNames())
    for option in declared:
        spec = definition.GetSchemaAttributeSpec(option.schema_attribute)
        expected = option.schema_unset if option.default is None else option.default
        if option.choices:
            assert spec.default == expected, option.name
            assert tuple(spec.allowedTokens) == option.choices, option.name
        else:  # a float attribute holds float32: 1e-6 is well above its rounding
            assert spec.default == pytest.approx(expected, rel=1e-6), option.name
    assert (schema.DEFAULT_BOUNCE_LIMIT, schema.DEFAULT_HEURISTIC) == (5, "heu1")
    assert schema.MODES == OPTIONS["mode"].choices


def test_probe_options_declared_in_many_places_cli_help():
    """`phrt render` and `phrt sweep` take each render option's help from the table, and
    sweep's defaults too; every choice of an option is named in its help or metavar."""
    command = typer.main.get_command(app)
    context = command.make_context("phrt", ["render"], resilient_parsing=True)
    for sub in ("render", "sweep"):
        params = {p.name: p for p in command.get_command(context, sub).params}
        for name, option in OPTIONS.items():
            given = "resolution" if name in SIZE else name
            if given not in params:
                continue  # e.g. sweep sweeps heuristics and budgets as lists
            assert params[given].help.startswith(option.help), (sub, name)
    sweep = {p.name: p for p in command.get_command(context, "sweep").params}
    assert sweep["bounce_limit"].default == OPTIONS["bounce_limit"].default
    assert sweep["resolution"].default == "320x240"
    for option in OPTIONS.values():
        shown = f"{option.help} {option.metavar or ''}"
        assert all(choice in shown for choice in option.choices), option.name


def test_set_up_and_frame_options_are_apart():
    """SetupOptions holds what a render is set up with, FrameOptions what every frame
    reads; together they are RenderOptions' fields, each option in exactly one part."""
    setup = {f.name for f in fields(SetupOptions)}
    frame = {f.name for f in fields(FrameOptions)}
    assert setup == {n for n, o in OPTIONS.items() if o.group == SETUP}
    assert frame == {n for n, o in OPTIONS.items() if o.group == FRAME}
    assert not setup & frame and {f.name for f in fields(RenderOptions)} == setup | frame
    options = RenderOptions(mode="raster", width=64, height=48, budget_rays=500, gl="EGL")
    assert isinstance(options, SetupOptions) and isinstance(options, FrameOptions)
    assert options.setup == SetupOptions(mode="raster", width=64, height=48, gl="egl")
    assert options.frame == FrameOptions(budget_rays=500)
    with pytest.raises(BadOption, match="--budget-ms and --target-fps both given"):
        FrameOptions(target_fps=30.0)  # the default 10 ms budget as well


#: Each option's bad value and its message, as the CLI and the API have always said it.
BAD_VALUES = [
    ({"mode": "fast"}, "unknown mode 'fast'; expected one of hybrid, rt, raster"),
    ({"mode": "RT"}, "unknown mode 'RT'"),  # USD tokens are case-sensitive
    ({"heuristic": "best"}, "unknown heuristic 'best'; expected one of heu1, heu2, all, none"),
    ({"width": 0, "height": 10}, "resolution 0x10 out of range 1..16384"),
    ({"width": 16384, "height": 16384}, "resolution 16384x16384: more than 67108864 pixels"),
    ({"width": 3.5}, "width must be an integer, got 3.5"),
    ({"budget_ms": -1.0}, "--budget-ms must be a finite number >= 0, got -1.0"),
    ({"budget_ms": math.inf}, "--budget-ms must be a finite number >= 0, got inf"),
    ({"budget_ms": "10"}, "budget_ms must be a number, got '10'"),
    ({"budget_rays": -1}, "--budget-rays must be in 0..1000000000000, got -1"),
    ({"budget_ms": None, "target_fps": 0.0}, r"--target-fps must be in \(0, 1000\], got 0.0"),
    ({"bounce_limit": 17}, "bounce limit must be in 0..16, got 17"),
    ({"bounce_limit": True}, "bounce_limit must be an integer, got True"),
    ({"selection_weight": -1.0}, "selection weight I must be a finite number >= 0, got -1.0"),
    ({"selection_weight": math.nan}, "selection_weight must be a number, got nan"),
    ({"threads": 0}, r"threads must be in 1\.\.1024, got 0"),
    ({"gl": "vulkan"}, "gl must be one of auto, egl, osmesa, got 'vulkan'"),
    ({"primary": "gpu"}, "primary must be one of auto, raster, rays, got 'gpu'"),
    ({"trace_density": "17/16"}, "trace density must be one of full, 15/16, 14/16"),
    ({"exposure": math.inf}, "--exposure must be a finite number of EV, got inf"),
    ({"mode": "rt", "primary": "raster"}, "--primary raster: rt mode traces every ray"),
    ({"mode": "rt", "trace_density": "half"}, "--trace-density half: rt mode traces every"),
]


@pytest.mark.parametrize("options,message", BAD_VALUES, ids=lambda v: str(v)[:32])
def test_every_bad_value_is_one_line_through_the_checks(options, message):
    with pytest.raises(BadOption, match=f"^{message}") as error:
        RenderOptions(**options)
    assert "\n" not in str(error.value)


def test_values_are_held_as_a_render_holds_them():
    """Checked values come back as the option holds them: floats, ints, lower case."""
    options = RenderOptions(
        budget_ms=np.int64(4), budget_rays=np.int64(9), exposure=1, primary="RAYS",
        trace_density="Half", bounce_limit=np.int32(2),
    )  # fmt: skip
    assert type(options.budget_ms) is float and type(options.budget_rays) is int
    assert (options.primary, options.trace_density, options.exposure) == ("rays", "half", 1.0)
    assert type(options.bounce_limit) is int and options.exposure_ev == 1.0
    assert RenderOptions(exposure=-90.0).exposure_ev == -40.0  # clamped to MAX_EXPOSURE_EV


def test_sweep_spec_takes_its_defaults_and_checks_from_the_table():
    spec = SweepSpec(stages=[], heuristics=["heu1"], budgets_ms=[2, None],
                     trace_densities=["HALF"], gl="OSMesa")  # fmt: skip
    for name in ("width", "height", "bounce_limit", "selection_weight", "threads", "exposure"):
        assert getattr(spec, name) == OPTIONS[name].default, name
    assert (spec.gl, spec.trace_densities, spec.budgets_ms) == ("osmesa", ["half"], [2.0, None])
    with pytest.raises(BadOption, match="bounce limit must be in 0..16, got 17"):
        SweepSpec(stages=[], heuristics=["heu1"], bounce_limits=[1, 17])
    with pytest.raises(BadOption, match="gl must be one of"):
        SweepSpec(stages=[], heuristics=["heu1"], gl="metal")


def test_checks_name_the_value_in_one_line():
    """The value checks' messages: the name given, what it must be, what it got."""
    cases = [
        (lambda: check_number(True, "x"), "x must be a number, got True"),
        (lambda: check_number(math.nan, "x"), "x must be a number, got nan"),
        (lambda: check_integer(1.5, "n"), "n must be an integer, got 1.5"),
        (lambda: check_bool("yes", "resume"), "resume must be True or False, got 'yes'"),
        (lambda: check_finite(math.inf, "time", "a finite time code"),
         "time must be a finite time code, got inf"),
        (lambda: check_range(0, 1, None, "every"), "every must be >= 1, got 0"),
        (lambda: check_range(5, 0, 4, "n"), r"n must be in 0\.\.4, got 5"),
        (lambda: check_range(-0.5, 0.0, None, "w"), "w must be a finite number >= 0, got -0.5"),
        (lambda: check_range(2.0, 0.0, 1.0, "f"), r"f must be in \[0, 1\], got 2.0"),
        (lambda: check_range(0.0, 0.0, 1.0, "f", low_open=True), r"f must be in \(0, 1\]"),
        (lambda: check_choice(3, ("a", "b"), "c"), "c must be one of a, b, got 3"),
        (lambda: check_token("A", ("a", "b"), "mode"), "unknown mode 'A'; expected one of a, b"),
    ]  # fmt: skip
    for call, message in cases:
        with pytest.raises(BadOption, match=f"^{message}"):
            call()
    assert check_choice("B", ("a", "b"), "c") == "b" and check_integer(np.int64(3), "n") == 3
    assert check_range(0.5, 0.0, 1.0, "f") == 0.5 and check_token("a", ("a",), "m") == "a"
