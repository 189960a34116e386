"""``phrt validate``: the UsdValidation framework on a stage, USD's own validators and the
Phrt validators (``phrt_usd.usd.validators``, the rules of ``phrt_usd.usd.rules``) in
one ``ValidationContext``, each finding one ``Issue`` line.

Phrt findings keep the rules' own issue, so their lines are the render's messages
(``ERROR /World/Mirror.phrt:priority: must be ...``); USD's findings are located at their
first prim or property site and end in ``[validator identifier]``. Severity: ``error``
makes the stage unusable or wrong for rendering (exit 1 in ``phrt validate``);
``warning`` is suspicious but renders. USD's Error is an error, Warn/Info a warning.
``usdValidation:CompositionErrorTest`` is left out: the Phrt CompositionChecker reports
each missing arc once, naming the prim, and USD's other findings about the same missing
asset are dropped.

Order: USD's findings by validator and location, then the Phrt validators' in the order
of ``VALIDATOR_NAMES``, each in the order its rules report (prim validators by prim).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from pxr import Sdf, Tf, Usd, UsdValidation

from phrt_usd.errors import usd_error_reason
from phrt_usd.usd import materialx, validators
from phrt_usd.usd.composition import composition_problems
from phrt_usd.usd.rules import ERROR, WARNING, Issue, stage_reflectors
from phrt_usd.usd.stage import open_usd

__all__ = ["ERROR", "WARNING", "Issue", "ValidationReport", "validate_file", "validate_stage"]


@dataclass(frozen=True)
class ValidationReport:
    """``reflectors``: every reflector prim path, instance proxies included
    (``rules.stage_reflectors``); ``instanced_reflectors``: those inside instances."""

    stage: str
    issues: list[Issue]
    reflectors: list[str] = field(default_factory=list)
    instanced_reflectors: list[str] = field(default_factory=list)

    @property
    def errors(self) -> list[Issue]:
        return [i for i in self.issues if i.severity == ERROR]

    @property
    def warnings(self) -> list[Issue]:
        return [i for i in self.issues if i.severity == WARNING]

    @property
    def ok(self) -> bool:
        return not self.errors

    def as_dict(self) -> dict:
        return {
            "stage": self.stage,
            "ok": self.ok,
            "errors": [i.as_dict() for i in self.errors],
            "warnings": [i.as_dict() for i in self.warnings],
            "reflectors": list(self.reflectors),
            "instanced_reflectors": list(self.instanced_reflectors),
        }


# --- the framework -------------------------------------------------------------------------
#: Replaced by the Phrt CompositionChecker (one line per missing arc, naming the prim).
_REPLACED_VALIDATORS = ("usdValidation:CompositionErrorTest",)
_UNRESOLVABLE = re.compile(r"unresolvable external dependency '(?P<asset>[^']*)'")
#: USD's finding that a Shader's ``info:id`` is not in its shader registry. usd-core ships
#: no usdMtlx, so every MaterialX node id (``ND_*``) is missing there, though a USD with
#: usdMtlx knows it and the render reads the MaterialX it maps (``usd/materialx.py``): an
#: id that MaterialX's standard library defines is no error (``_materialx_id``).
_MISSING_SHADER_ID = "MissingShaderIdInRegistry"
_SHADER_ID = re.compile(r"shaderId '(?P<id>[^']*)'")
_PHRT_RANK = {name: rank for rank, name in enumerate(validators.VALIDATOR_NAMES)}


def _chosen_validators() -> list[UsdValidation.Validator]:
    """Every validator USD knows (the Phrt ones included), less the replaced ones."""
    registry = UsdValidation.ValidationRegistry()
    chosen = [
        v
        for v in registry.GetOrLoadAllValidators()
        if v.GetMetadata().name not in _REPLACED_VALIDATORS
    ]
    names = {v.GetMetadata().name for v in chosen}
    missing = [n for n in validators.VALIDATOR_NAMES if n not in names]
    if missing:  # registered by the import above; a USD that dropped them is a bug
        raise RuntimeError(f"Phrt validators not registered: {', '.join(missing)}")
    return chosen


def _context() -> UsdValidation.ValidationContext:
    """One context of ``_chosen_validators``."""
    return UsdValidation.ValidationContext(_chosen_validators())


def _site_where(err: UsdValidation.ValidationError) -> str:
    for site in err.GetSites():
        if site.IsProperty():
            return str(site.GetProperty().GetPath())
        if site.IsPrim():
            return str(site.GetPrim().GetPath())
    return "/"


def _severity(err: UsdValidation.ValidationError) -> str:
    return ERROR if err.GetType() == UsdValidation.ValidationErrorType.Error else WARNING


def _prim_of(where: str) -> str:
    """The prim path a location sorts by (``where`` itself when it is not a path)."""
    if Sdf.Path.IsValidPathString(where) and where.startswith("/"):
        return str(Sdf.Path(where).GetPrimPath())
    return where


def _run_validators(stage: Usd.Stage, missing: set[str]) -> tuple[list, list[Issue]]:
    """Every validator's findings, and one error per reason USD stopped validators with
    (a ``Tf`` error: a layer they read, a referenced layer, a usdz member or a layer of
    an unselected variant, does not parse). One context runs them all; only when it
    stops does each run on its own, so the others' findings are kept. A stop about a
    layer the CompositionChecker already reports (``missing``) is not repeated."""
    try:
        return list(_context().Validate(stage)), []
    except Tf.ErrorException:
        pass
    found: list = []
    stopped: dict[str, list[str]] = {}  # reason -> validators it stopped
    for validator in _chosen_validators():
        try:
            found += UsdValidation.ValidationContext([validator]).Validate(stage)
        except Tf.ErrorException as error:
            reason = usd_error_reason(error)
            if not any(asset in reason for asset in missing):
                stopped.setdefault(reason, []).append(validator.GetMetadata().name)
    return found, [_stop_issue(stage, reason, names) for reason, names in stopped.items()]


#: ``<file>:<line>:<column>: <what>``, the form of a parser's reason.
_LOCATED_REASON = re.compile(r"^(?P<where>\S.*?:\d+:\d+): (?P<what>.*)$")


def _materialx_id(identifier: str, message: str) -> bool:
    """USD's finding ``identifier`` / ``message`` is only that this USD's shader
    registry lacks a MaterialX node definition (``_MISSING_SHADER_ID``)."""
    if not identifier.endswith(_MISSING_SHADER_ID):
        return False
    m = _SHADER_ID.search(message)
    return bool(m) and m["id"].startswith("ND_") and materialx.defines_node(m["id"])


def _stop_issue(stage: Usd.Stage, reason: str, names: list[str]) -> Issue:
    """The error for validators USD stopped: located at the parser's ``file:line:column``
    when the reason gives one, else at the stage's root layer."""
    m = _LOCATED_REASON.match(reason)
    where, what = (m["where"], m["what"]) if m else (stage.GetRootLayer().identifier, reason)
    stopped = ", ".join(sorted(names))
    return Issue(ERROR, where, f"{what} (USD stopped these validators here) [{stopped}]")


def validate_stage(stage: Usd.Stage, label: str | None = None) -> ValidationReport:
    """USD's validators and the Phrt validators on an open stage, in one context
    (``_run_validators``)."""
    name = label or stage.GetRootLayer().identifier
    missing = {p.asset for p in composition_problems(stage) if p.asset}
    usd, phrt = [], []
    found, stopped = _run_validators(stage, missing)
    for err in found:
        if err.HasNoError():
            continue
        validator = err.GetValidator().GetMetadata().name
        severity = _severity(err)
        if validator in _PHRT_RANK:
            issue = Issue.of(severity, err.GetMessage(), err.GetName())
            per_prim = validator in validators.PRIM_VALIDATORS
            phrt.append((_PHRT_RANK[validator], _prim_of(issue.where) if per_prim else "", issue))
            continue
        message = " ".join(err.GetMessage().split())
        m = _UNRESOLVABLE.search(message)
        if m and m["asset"] in missing:
            continue  # the same missing layer, already reported with its prim
        if _materialx_id(err.GetIdentifier(), message):
            continue
        where = _site_where(err)
        usd.append((validator, where, Issue(severity, where, f"{message} [{err.GetIdentifier()}]")))
    usd += [(issue.message.rpartition("[")[2], issue.where, issue) for issue in stopped]
    # Stable sorts: a task's own findings keep their order (a context keeps them together).
    usd.sort(key=lambda t: (t[0], t[1]))
    phrt.sort(key=lambda t: (t[0], t[1]))
    reflectors = stage_reflectors(stage)
    return ValidationReport(
        name,
        [t[2] for t in usd] + [t[2] for t in phrt],
        reflectors=[str(p.GetPath()) for p in reflectors],
        instanced_reflectors=[str(p.GetPath()) for p in reflectors if p.IsInstanceProxy()],
    )


def validate_file(path: str | Path) -> ValidationReport:
    """Open and validate; PhrtError when the file cannot be opened as USD."""
    return validate_stage(open_usd(path), str(path))
