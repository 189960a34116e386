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

from pxr import Sdf, Usd, UsdValidation

from phrt_usd.usd import validators
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
_PHRT_RANK = {name: rank for rank, name in enumerate(validators.VALIDATOR_NAMES)}


def _context() -> UsdValidation.ValidationContext:
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
    return UsdValidation.ValidationContext(chosen)


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


def validate_stage(stage: Usd.Stage, label: str | None = None) -> ValidationReport:
    """USD's validators and the Phrt validators on an open stage, in one context."""
    name = label or stage.GetRootLayer().identifier
    missing = {p.asset for p in composition_problems(stage) if p.asset}
    usd, phrt = [], []
    for err in _context().Validate(stage):
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
        where = _site_where(err)
        usd.append((validator, where, Issue(severity, where, f"{message} [{err.GetIdentifier()}]")))
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
