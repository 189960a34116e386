"""The Phrt rules as ``UsdValidation`` validators: the python plugin module that
``phrt_usd/usd/plugin/plugInfo.json`` names (``phrt_usd.usd.validators``).

The plugin declares the validators (name, doc, keywords ``PhrtUsdValidators``, schema
types) in its ``Validators`` metadata, so any USD tool finds them with
``PXR_PLUGINPATH_NAME`` pointing at the plugin folder, and USD imports this module (from
the Python it runs in, where phrt-usd must be installed) the first time a validator is
asked for; importing it registers each validator's task here. ``phrt validate`` imports it
itself (``phrt_usd.usd.validation``).

Validators (each a thin task over ``phrt_usd.usd.rules``, the one implementation):

- ``phrt_usd.usd.validators:CompositionChecker`` (stage): ``rules.composition_issues``;
- ``phrt_usd.usd.validators:RenderChecker`` (stage): ``rules.render_issues``, the render's
  own rules, checked at the render's time codes (the validation time range is not used);
- ``phrt_usd.usd.validators:RenderSettingsChecker`` (prim, schema type
  ``PhrtUsdRenderSettingsAPI``): ``rules.render_settings_issues``;
- ``phrt_usd.usd.validators:PhrtRules``: the suite of the three.

Every ``ValidationError`` carries the issue's message in the render's own form,
``"<where>: <text>"`` (``Issue.text()``; ``Issue.of`` reads it back), its name is the
rule group (``Issue.rule``: ``Camera``, ``Geometry``, ...), its type Error or Warn and its
site the prim or property of ``where`` (the layer for layer-level problems). A task that
fails reports its exception as one error instead of raising into the tool.
"""

from __future__ import annotations

from collections.abc import Callable

from pxr import Plug, Sdf, Usd, UsdValidation

from phrt_usd.errors import PhrtError
from phrt_usd.usd import rules
from phrt_usd.usd.rules import ERROR, Issue

#: The plugin's name in plugInfo.json: this module, as USD imports it.
PLUGIN_NAME = "phrt_usd.usd.validators"
COMPOSITION_CHECKER = f"{PLUGIN_NAME}:CompositionChecker"
RENDER_CHECKER = f"{PLUGIN_NAME}:RenderChecker"
RENDER_SETTINGS_CHECKER = f"{PLUGIN_NAME}:RenderSettingsChecker"
SUITE = f"{PLUGIN_NAME}:PhrtRules"
#: The Phrt validators, in the order ``phrt validate`` reports their issues.
VALIDATOR_NAMES = (COMPOSITION_CHECKER, RENDER_CHECKER, RENDER_SETTINGS_CHECKER)
#: The validators called once per prim (of their schema types); the others once per stage.
PRIM_VALIDATORS = (RENDER_SETTINGS_CHECKER,)
#: The error name of a task that raised.
TASK_FAILED = "TaskFailed"

_TYPES = {
    ERROR: UsdValidation.ValidationErrorType.Error,
    rules.WARNING: UsdValidation.ValidationErrorType.Warn,
}


def _site(stage: Usd.Stage, where: str) -> UsdValidation.ValidationErrorSite:
    """The layer ``where`` names (layer-level problems), else the stage's prim or property
    at that path, else the stage's pseudo-root."""
    layer = Sdf.Layer.Find(where)
    if layer is not None:
        return UsdValidation.ValidationErrorSite(layer, Sdf.Path.absoluteRootPath)
    if where.startswith("/") and Sdf.Path.IsValidPathString(where):
        if stage.GetObjectAtPath(Sdf.Path(where)):
            return UsdValidation.ValidationErrorSite(stage, Sdf.Path(where))
    return UsdValidation.ValidationErrorSite(stage, Sdf.Path.absoluteRootPath)


def to_errors(stage: Usd.Stage, issues: list[Issue]) -> list[UsdValidation.ValidationError]:
    return [
        UsdValidation.ValidationError(
            issue.rule or "Problem", _TYPES[issue.severity], [_site(stage, issue.where)],
            issue.text(),
        )
        for issue in issues
    ]  # fmt: skip


def _guarded(stage: Usd.Stage, name: str, check: Callable[[], list[Issue]]):
    """Run one rule group; a PhrtError is a problem of the stage (one error, the
    render's message), anything else a failure of the validator, reported, not raised."""
    try:
        return to_errors(stage, check())
    except PhrtError as exc:
        return to_errors(stage, [Issue.of(ERROR, str(exc), "Stage")])
    except Exception as exc:  # noqa: BLE001 - a tool's whole validation must not abort
        message = f"{name} failed: {type(exc).__name__}: {' '.join(str(exc).split())}"
        return to_errors(stage, [Issue(ERROR, "/", message, TASK_FAILED)])


def composition_task(stage: Usd.Stage, time_range=None) -> list[UsdValidation.ValidationError]:
    return _guarded(stage, COMPOSITION_CHECKER, lambda: rules.composition_issues(stage))


def render_task(stage: Usd.Stage, time_range=None) -> list[UsdValidation.ValidationError]:
    return _guarded(stage, RENDER_CHECKER, lambda: rules.render_issues(stage))


def render_settings_task(prim: Usd.Prim, time_range=None) -> list[UsdValidation.ValidationError]:
    return _guarded(
        prim.GetStage(), RENDER_SETTINGS_CHECKER, lambda: rules.render_settings_issues(prim)
    )


_TASKS = {
    COMPOSITION_CHECKER: ("stage", composition_task),
    RENDER_CHECKER: ("stage", render_task),
    RENDER_SETTINGS_CHECKER: ("prim", render_settings_task),
}


def _declared_metadata(name: str) -> UsdValidation.ValidatorMetadata:
    """The metadata plugInfo.json declares for ``name``, for a registry created before the
    plugin was registered (it read the plugins' metadata once, without ours)."""
    plugin = Plug.Registry().GetPluginWithName(PLUGIN_NAME)
    if plugin is None:
        raise RuntimeError(f"{PLUGIN_NAME}: plugin not registered (import phrt_usd first)")
    declared = dict(plugin.metadata.get("Validators", {}))
    shared = list(declared.pop("keywords", []))
    entry = declared[name.partition(":")[2]]
    return UsdValidation.ValidatorMetadata(
        name=name,
        plugin=plugin,
        keywords=shared + list(entry.get("keywords", [])),
        doc=entry.get("doc", ""),
        schemaTypes=list(entry.get("schemaTypes", [])),
        isSuite=bool(entry.get("isSuite", False)),
    )


def _register() -> None:
    registry = UsdValidation.ValidationRegistry()
    for name, (kind, task) in _TASKS.items():
        if registry.HasValidator(name):
            continue
        if registry.GetValidatorMetadata(name) is not None:
            if kind == "stage":
                registry.RegisterPluginStageValidator(name, task)
            else:
                registry.RegisterPluginPrimValidator(name, task)
        elif kind == "stage":
            registry.RegisterStageValidator(_declared_metadata(name), task)
        else:
            registry.RegisterPrimValidator(_declared_metadata(name), task)
    if not registry.HasValidatorSuite(SUITE):
        members = [registry.GetOrLoadValidatorByName(n) for n in VALIDATOR_NAMES]
        if registry.GetValidatorMetadata(SUITE) is not None:
            registry.RegisterPluginValidatorSuite(SUITE, members)
        else:
            registry.RegisterValidatorSuite(_declared_metadata(SUITE), members)


_register()
