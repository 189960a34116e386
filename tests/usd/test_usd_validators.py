"""The Phrt rules as UsdValidation validators: found by plain USD through
PXR_PLUGINPATH_NAME, the same findings as ``phrt validate``, and the plugin files that
usd-core's usdGenSchema generates."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from pxr import Tf, Usd, UsdValidation
from repo_paths import REPO
from scenes import clean_stage

import phrt_usd
from phrt_usd.usd import schema, validators
from phrt_usd.usd.validation import validate_stage

GEN_SCHEMA = REPO / "tools" / "gen_schema.py"

#: A script for a Python that never imports phrt_usd: plain USD finds the Phrt validators
#: from the plugin's plugInfo.json, loads them and runs them on the stage in argv[1].
FOREIGN_TOOL = """
import json, sys
from pxr import Usd, UsdValidation
registry = UsdValidation.ValidationRegistry()
declared = sorted(m.name for m in registry.GetValidatorMetadataForKeyword("PhrtUsdValidators"))
by_type = [m.name for m in registry.GetValidatorMetadataForSchemaType("PhrtUsdRenderSettingsAPI")]
loaded_before = "phrt_usd" in sys.modules
suite = registry.GetOrLoadValidatorSuiteByName("phrt_usd.usd.validators:PhrtRules")
stage = Usd.Stage.Open(sys.argv[1])
found = []
for err in UsdValidation.ValidationContext([suite]).Validate(stage):
    sites = [str(s.GetProperty().GetPath() if s.IsProperty() else s.GetPrim().GetPath())
             for s in err.GetSites() if s.IsPrim() or s.IsProperty()]
    found.append({"id": err.GetIdentifier(), "type": str(err.GetType()).rpartition(".")[2],
                  "message": err.GetMessage(), "sites": sites})
print(json.dumps({"declared": declared, "by_type": by_type, "loaded_before": loaded_before,
                  "suite": sorted(v.GetMetadata().name for v in suite.GetContainedValidators()),
                  "found": found}))
"""


def run_foreign_tool(stage_path: Path, cwd: Path) -> dict:
    env = dict(os.environ, PXR_PLUGINPATH_NAME=str(phrt_usd.PLUGIN_DIR))
    proc = subprocess.run(
        [sys.executable, "-c", FOREIGN_TOOL, str(stage_path)],
        env=env, capture_output=True, text=True, timeout=120, cwd=cwd,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.fixture()
def planted(tmp_path):
    """clean_stage with two planted problems: K < 0 on the mirror, bounce limit 17."""
    path = tmp_path / "planted.usda"
    stage = clean_stage(path)
    stage.GetPrimAtPath("/World/Mirror").GetAttribute(schema.PRIORITY).Set(-1.0)
    stage.GetPrimAtPath("/World/Render").GetAttribute(schema.BOUNCE_LIMIT).Set(17)
    stage.GetRootLayer().Save()
    return path


@pytest.mark.slow
def test_a_tool_that_never_imports_phrt_usd_finds_and_runs_the_phrt_validators(tmp_path, planted):
    out = run_foreign_tool(planted, tmp_path)
    assert out["declared"] == sorted([*validators.VALIDATOR_NAMES, validators.SUITE])
    assert out["by_type"] == [validators.RENDER_SETTINGS_CHECKER]  # the TfType name matches
    assert out["loaded_before"] is False  # discovery needs plugInfo.json only
    assert out["suite"] == sorted(validators.VALIDATOR_NAMES)
    assert sorted(out["found"], key=lambda f: f["id"]) == [
        {
            "id": "phrt_usd.usd.validators:RenderChecker.Geometry",
            "type": "Error",
            "message": "/World/Mirror.phrt:priority: must be a finite number >= 0, got -1.0",
            "sites": ["/World/Mirror.phrt:priority"],
        },
        {
            "id": "phrt_usd.usd.validators:RenderSettingsChecker.RenderSettings",
            "type": "Error",
            "message": "/World/Render.phrt:bounceLimit: bounce limit 17 (need 0..16)",
            "sites": ["/World/Render.phrt:bounceLimit"],
        },
    ]


@pytest.mark.slow
def test_a_clean_stage_gives_the_foreign_tool_no_phrt_finding(tmp_path):
    path = tmp_path / "clean.usda"
    stage = clean_stage(path)
    stage.GetRootLayer().Save()
    assert run_foreign_tool(path, tmp_path)["found"] == []


def test_phrt_validate_reports_the_validators_findings_as_its_lines(planted):
    report = validate_stage(Usd.Stage.Open(str(planted)))
    assert [i.line() for i in report.errors] == [
        "ERROR /World/Mirror.phrt:priority: must be a finite number >= 0, got -1.0",
        "ERROR /World/Render.phrt:bounceLimit: bounce limit 17 (need 0..16)",
    ]
    assert [i.rule for i in report.errors] == ["Geometry", "RenderSettings"]


def test_every_schema_type_of_a_validator_is_a_registered_type_name():
    """USD matches schemaTypes against TfType names only: an alias is never called."""
    registry = UsdValidation.ValidationRegistry()
    for name in validators.VALIDATOR_NAMES:
        for type_name in registry.GetValidatorMetadata(name).GetSchemaTypes():
            found = Tf.Type.FindByName(type_name)
            assert not found.isUnknown and found.typeName == type_name, (name, type_name)


def test_a_failing_rule_is_one_error_not_an_exception(tmp_path, monkeypatch):
    def broken(stage):
        raise ValueError("no\nluck")

    monkeypatch.setattr(validators.rules, "render_issues", broken)
    stage = clean_stage(tmp_path / "s.usda")
    (err,) = validators.render_task(stage)
    assert err.GetName() == validators.TASK_FAILED
    assert err.GetMessage() == (
        "/: phrt_usd.usd.validators:RenderChecker failed: ValueError: no luck"
    )
    assert [i.line() for i in validate_stage(stage).errors] == [
        "ERROR /: phrt_usd.usd.validators:RenderChecker failed: ValueError: no luck"
    ]


@pytest.mark.slow
def test_validators_registered_when_the_registry_came_before_phrt_usd(tmp_path, planted):
    """A process that built USD's validation registry before importing phrt_usd (so
    without the plugin's metadata) still runs the Phrt rules in phrt validate."""
    code = (
        "import sys\n"
        "from pxr import UsdValidation\n"
        "UsdValidation.ValidationRegistry().GetOrLoadAllValidators()\n"
        "from phrt_usd.usd.validation import validate_file\n"
        "meta = UsdValidation.ValidationRegistry().GetValidatorMetadata(\n"
        "    'phrt_usd.usd.validators:RenderChecker')\n"
        "print(meta.GetKeywords())\n"
        f"print(validate_file({str(planted)!r}).errors[0].line())\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PXR_PLUGINPATH_NAME"}
    proc = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120,
        cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [
        "['PhrtUsdValidators']",
        "ERROR /World/Mirror.phrt:priority: must be a finite number >= 0, got -1.0",
    ]


# --- the plugin files are usdGenSchema's -------------------------------------------------
def gen_schema(*args):
    return subprocess.run(
        [sys.executable, str(GEN_SCHEMA), *map(str, args)],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


@pytest.mark.slow
def test_checked_in_plugin_is_what_usdgenschema_generates(tmp_path):
    fresh = tmp_path / "fresh"
    proc = gen_schema("--out", fresh)
    assert proc.returncode == 0, proc.stderr
    for name in ("generatedSchema.usda", "plugInfo.json"):
        assert (fresh / name).read_text() == (phrt_usd.PLUGIN_DIR / name).read_text(), name
    assert (
        (fresh / "plugInfo.json")
        .read_text()
        .startswith("# Portions of this file auto-generated by usdGenSchema.")
    )
    assert "GENERATED BY usdGenSchema" in (fresh / "generatedSchema.usda").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("edit", ["types", "validators", "schema doc"])
def test_check_finds_a_stale_plugin(tmp_path, edit):
    plugin = tmp_path / "plugin"
    shutil.copytree(phrt_usd.PLUGIN_DIR, plugin)
    assert gen_schema("--check", "--out", plugin).returncode == 0
    info, usda = plugin / "plugInfo.json", plugin / "generatedSchema.usda"
    if edit == "types":
        info.write_text(info.read_text().replace('"Gprim"', '"Mesh"'))
    elif edit == "validators":
        info.write_text(
            info.read_text().replace("PhrtUsdRenderSettingsAPI", "PhrtRenderSettingsAPI")
        )
    else:
        usda.write_text(usda.read_text().replace("Marks a gprim", "Marks a prim"))
    proc = gen_schema("--check", "--out", plugin)
    assert proc.returncode == 1
    assert proc.stderr.startswith("stale: ") and "\n" == proc.stderr[-1]


def test_sites_name_the_layer_the_property_or_the_stage(tmp_path):
    path = tmp_path / "s.usda"
    stage = clean_stage(path)
    stage.RemovePrim("/World/Path")
    stage.RemovePrim("/World/Cam")
    (err,) = validators.render_task(stage)  # a warning: a default camera frames the stage
    assert err.GetMessage() == (
        f"{path}: stage has no UsdGeomCamera: the render uses a default camera framing the "
        "stage's bounds"
    )
    assert err.GetType() == UsdValidation.ValidationErrorType.Warn
    (site,) = err.GetSites()
    assert site.GetLayer().identifier == str(path) and not site.IsPrim()
    stage.GetPrimAtPath("/World/Render").GetAttribute(schema.MODE).Set("fast")
    (err,) = validators.render_settings_task(stage.GetPrimAtPath("/World/Render"))
    assert str(err.GetSites()[0].GetProperty().GetPath()) == "/World/Render.phrt:mode"
