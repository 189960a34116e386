"""What a pipeline asks of a stage's composition when phrt opens it, as ``husk`` and
``usdrecord`` take it: session layers, variant selections and a population mask.

``StageControls`` holds them as plain values (recorded with the run, part of its
identity); ``session_layer`` builds the in-memory session layer that carries them
(the given session layers as its sublayers, strongest first, then the variant selections
as ``over``s, which are stronger still); ``population_mask`` the ``Usd.StagePopulationMask``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from pxr import Sdf, Tf, Usd

from phrt_usd.errors import BadOption, usd_error_reason


@dataclass(frozen=True)
class StageControls:
    """session_layers: layer files, strongest first (``--session-layer``, repeatable);
    variants: (prim path, variant set, variant name) selections (``--variant``);
    mask: prim paths the stage is populated with (``--mask``), empty for all."""

    session_layers: tuple[str, ...] = ()
    variants: tuple[tuple[str, str, str], ...] = ()
    mask: tuple[str, ...] = ()

    @classmethod
    def from_options(
        cls, session_layers=(), variants=(), mask: str | None = None
    ) -> StageControls:
        """From the CLI's ``--session-layer FILE``s, ``--variant PRIM:SET=NAME``s and
        ``--mask PRIM,...``; BadOption (one line) for a malformed value, or a session
        layer that is missing, a directory or another file that is not a regular one,
        or that USD cannot read (with USD's reason, a parser's ``file:line:column``)."""
        layers = []
        for path in session_layers:
            path = os.fspath(path)
            if not os.path.exists(path):
                raise BadOption(f"--session-layer {path}: no such file")
            if os.path.isdir(path):
                raise BadOption(f"--session-layer {path}: is a directory, not a USD layer")
            if not os.path.isfile(path):
                raise BadOption(f"--session-layer {path}: not a regular file "
                                "(a device, pipe or socket)")  # fmt: skip
            try:
                readable = Sdf.Layer.FindOrOpen(path) is not None
                reason = "not a USD layer"
            except Tf.ErrorException as error:
                readable, reason = False, usd_error_reason(error)
            if not readable:
                raise BadOption(f"--session-layer {path}: cannot open ({reason})")
            layers.append(os.path.abspath(path))
        parsed = tuple(parse_variant(v) for v in variants)
        masked = tuple(p.strip() for p in (mask or "").split(",") if p.strip())
        for path in masked:
            _check_prim_path(path, "--mask")
        return cls(tuple(layers), parsed, masked)

    def __bool__(self) -> bool:
        return bool(self.session_layers or self.variants or self.mask)

    def as_dict(self) -> dict:
        """Plain data for stats.json, the selection layer and the run identity."""
        return {
            "session_layers": list(self.session_layers),
            "variants": [f"{p}:{s}={n}" for p, s, n in self.variants],
            "mask": list(self.mask),
        }

    def session_layer(self) -> Sdf.Layer | None:
        """An anonymous session layer carrying the controls, or None without any. A
        selection USD cannot hold (a set or variant name that is no identifier, such as
        ``a.b``) names no variant of any stage: it is left out here, and ``check``
        refuses it once the stage is open, listing the variants there are."""
        if not (self.session_layers or self.variants):
            return None
        layer = Sdf.Layer.CreateAnonymous("phrt-session.usda")
        layer.subLayerPaths[:] = list(self.session_layers)
        for prim_path, variant_set, name in self.variants:
            spec = Sdf.CreatePrimInLayer(layer, Sdf.Path(prim_path))
            try:
                spec.variantSelections[variant_set] = name
            except Tf.ErrorException:
                continue  # not a variant name: ``check`` says which names there are
        return layer

    def population_mask(self) -> Usd.StagePopulationMask | None:
        return Usd.StagePopulationMask(self.mask) if self.mask else None

    def check(self, stage: Usd.Stage) -> None:
        """BadOption unless every variant selection names a prim, set and variant the
        stage has (a typo would otherwise render the default variant in silence)."""
        for prim_path, variant_set, name in self.variants:
            shown = f"--variant {prim_path}:{variant_set}={name}"
            prim = stage.GetPrimAtPath(prim_path)
            if not prim or not prim.IsDefined():  # our own over alone makes no prim
                raise BadOption(f"{shown}: no prim {prim_path} in the stage")
            sets = prim.GetVariantSets()
            if not sets.HasVariantSet(variant_set):
                known = ", ".join(sets.GetNames()) or "none"
                raise BadOption(f"{shown}: {prim_path} has no variant set {variant_set!r} "
                                f"(it has: {known})")  # fmt: skip
            names = sets.GetVariantSet(variant_set).GetVariantNames()
            if name not in names:
                known = ", ".join(names) or "none"
                raise BadOption(f"{shown}: {prim_path} has no variant {name!r} in its "
                                f"variant set {variant_set!r} (it has: {known})")  # fmt: skip


def parse_variant(text: str) -> tuple[str, str, str]:
    """``"/World/Car:paint=red"`` → ("/World/Car", "paint", "red"); BadOption otherwise."""
    prim, sep, rest = text.rpartition(":")
    variant_set, eq, name = rest.partition("=")
    if not (sep and eq and variant_set and name):
        raise BadOption(f"--variant {text!r}: expected PRIM:SET=NAME, e.g. /World/Car:paint=red")
    _check_prim_path(prim, "--variant")
    return prim, variant_set, name


def _check_prim_path(path: str, option: str) -> None:
    if not Sdf.Path.IsValidPathString(path) or not Sdf.Path(path).IsAbsolutePath():
        raise BadOption(f"{option} {path!r}: not an absolute prim path")
    if not Sdf.Path(path).IsPrimPath() and path != "/":
        raise BadOption(f"{option} {path!r}: not a prim path")
