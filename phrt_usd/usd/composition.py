"""Composition: the sublayers, references and payloads of a stage USD could not open.

``composition_problems`` lists them (and the stage's other composition errors) one each,
naming the prim or layer (but references and payloads of a ``.mtlx`` document that is
there: usd-core cannot compose it, the render reads it itself, ``usd/materialx.py``);
``phrt validate`` reports each as an error. The render goes on without them:
``composition_warnings`` turns them into the one-line warnings of ``StageScene.warnings``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from pxr import Pcp, Usd

from phrt_usd.usd import materialx


@dataclass(frozen=True)
class CompositionProblem:
    """One composition error of the stage (``Usd.Stage.GetCompositionErrors``).

    kind    : "sublayer", "reference", "payload", or "other" (any other Pcp error)
    where   : the prim whose arc failed; for a sublayer, the layer that lists it
    asset   : the asset path USD could not open, as USD resolved it ("" for "other")
    message : one line, ``"<where>: <what>"`` (``phrt validate`` reports it as an error)
    reason  : why USD could not open it, when USD says (a layer that does not parse:
              the parser's ``file:line:column: what``), else ""
    """

    kind: str
    where: str
    asset: str
    message: str
    reason: str = ""


_ASSET_ERROR = re.compile(
    r"Could not open asset @(?P<asset>.*?)@ for (?P<arc>\w+) introduced by "
    r"@(?P<layer>.*?)@<(?P<site>[^>]*)>\.?(?:\s*--\s*(?P<reason>.*?))?\.?$"
)
_SUBLAYER_ERROR = re.compile(
    r"Could not load sublayer @(?P<asset>.*?)@ of layer @(?P<layer>.*?)@"
    r"(?:\s*--\s*(?P<reason>.*?))?\s*(?:;\s*skipping)?\.?$"
)


def composition_problems(stage: Usd.Stage) -> list[CompositionProblem]:
    """Sublayers, references and payloads the stage names but USD could not open, and
    the stage's other composition errors, one each, sorted by location (USD's own order
    varies). Muted layers are intentional and not reported."""
    problems = []
    for err in stage.GetCompositionErrors():
        if err.errorType == Pcp.ErrorType_MutedAssetPath:
            continue
        text = " ".join(str(err).split())
        prim = str(err.rootSite.path)
        m = _ASSET_ERROR.search(text)
        if m and err.errorType == Pcp.ErrorType_InvalidAssetPath:
            if materialx.readable_document(m["asset"]):
                continue  # a MaterialX document: the render reads it (usd/materialx.py)
            arc = m["arc"] if m["arc"] in ("reference", "payload") else "reference"
            why = (m["reason"] or "").strip()
            reason = f" ({why})" if why else ""
            problems.append(
                CompositionProblem(
                    arc, prim, m["asset"], f"{prim}: cannot open {arc} {m['asset']}{reason}", why
                )
            )
            continue
        m = _SUBLAYER_ERROR.search(text)
        if m and err.errorType == Pcp.ErrorType_InvalidSublayerPath:
            why = (m["reason"] or "").strip()
            reason = f" ({why})" if why else ""
            problems.append(
                CompositionProblem(
                    "sublayer",
                    m["layer"],
                    m["asset"],
                    f"{m['layer']}: cannot open sublayer {m['asset']}{reason}",
                    why,
                )
            )
            continue
        problems.append(CompositionProblem("other", prim, "", f"{prim}: {text}"))
    return sorted(problems, key=lambda p: (p.where, p.message))


#: Prim paths listed in one composition warning before "and N more".
_WARNING_PATHS = 5


def composition_warnings(problems: list[CompositionProblem]) -> list[str]:
    """One-line render warnings for ``composition_problems``: per missing reference or
    payload asset, the number of prims that render without its content and their paths;
    per missing sublayer, the layer (the number of prims it held is unknown); each with
    USD's reason when it gives one (a parse error's ``file:line:column``)."""
    by_asset: dict[tuple[str, str, str], list[str]] = {}
    warnings = []
    for p in problems:
        why = f" ({p.reason})" if p.reason else ""
        if p.kind in ("reference", "payload"):
            by_asset.setdefault((p.kind, p.asset, why), []).append(p.where)
        elif p.kind == "sublayer":
            warnings.append(
                f"missing sublayer {p.asset}{why} of {p.where}: not rendered "
                "(how many prims it held is unknown)"
            )
        else:
            warnings.append(f"composition error: {p.message}")
    for (kind, asset, why), prims in by_asset.items():
        shown = ", ".join(prims[:_WARNING_PATHS])
        if len(prims) > _WARNING_PATHS:
            shown += f" and {len(prims) - _WARNING_PATHS} more"
        n = len(prims)
        count = "1 prim renders" if n == 1 else f"{n} prims render"
        warnings.append(f"missing {kind} {asset}{why}: {count} without its content ({shown})")
    return warnings
