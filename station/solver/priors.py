"""Prior standard deviations of the parameters (their manufacturing tolerances): defaults per group and
quantity, overridden by the model file's ``tolerances:`` and then by the caller (``--prior``).

Within one level the most specific selector wins (an exact name over a glob or group; a smaller group
over a larger one), so ``{"dh": 0.5mm, "dh.j2.a": 0.1mm}`` means what it says in any order. Nuisance
unknowns (reference points, the instrument frame) have no prior: the data alone determine them."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np

from station.solver.observations import SolverInputError

DEG = math.pi / 180.0

# (parameter-name prefix, quantity) -> default std (SI). First match wins; the last two are the fallback.
DEFAULTS: tuple[tuple[str, str, float], ...] = (
    ("offset.", "angle", 1.0 * DEG),  # joint zero: encoder/horn/homing assembly
    ("offset.", "length", 1e-3),  # prismatic zero
    ("tcp.", "length", 0.1),  # a tool is often not measured at all: the data must find it
    ("tcp.", "angle", 5.0 * DEG),
    ("base.", "length", 0.1),  # where the robot stands in the cell
    ("base.", "angle", 5.0 * DEG),
    # joint compliance, rad per N*m: weak on purpose (industrial arms are ~1e-6..1e-5, hobby servos
    # ~1e-3..1e-2 with their gear play): the gravity torques of the poses determine it
    ("compliance.", "compliance", 1e-2),
    ("", "length", 0.5e-3),  # link geometry (DH/MDH/POE lengths): machining and assembly
    ("", "angle", 0.2 * DEG),  # link twists, Hayati beta, POE frame rotations
)

Spec = tuple[str, float, "str | None"]  # (selector, std SI, "length" | "angle" | "compliance" | None = any)


def quantity_of(name: str, angles: set[str]) -> str:
    """``angle``, ``length`` or ``compliance`` (rad per N*m) of a parameter name."""
    if name.startswith("compliance."):
        return "compliance"
    return "angle" if name in angles else "length"


def default_std(name: str, quantity: str) -> float:
    for prefix, q, std in DEFAULTS:
        if name.startswith(prefix) and q == quantity:
            return std
    raise AssertionError("DEFAULTS ends with a fallback per quantity")  # pragma: no cover


def normalise(priors) -> list[Spec]:
    """``priors`` as given to ``solve``: None, ``{selector: std}`` (SI; the quantity follows from the
    parameters named) or an iterable of ``(selector, std, quantity)``."""
    if priors is None:
        return []
    mapping = isinstance(priors, Mapping)
    items: Iterable = priors.items() if mapping else priors
    out: list[Spec] = []
    for it in items:
        sel, std, *rest = it
        quantity = rest[0] if rest else ("implied" if mapping else None)
        try:
            std = float(std)
        except (TypeError, ValueError):
            raise SolverInputError(f"prior {sel!r}: standard deviation {std!r} is not a number") from None
        if not (math.isfinite(std) and std > 0):
            raise SolverInputError(f"prior {sel!r}: standard deviation must be a positive number, got {std!r}")
        if quantity not in (None, "implied", "length", "angle", "compliance"):
            raise SolverInputError(f"prior {sel!r}: quantity must be length, angle or compliance, got {quantity!r}")
        out.append((str(sel), std, quantity))
    return out


def prior_stds(model, names: list[str], angles: set[str], priors=None) -> np.ndarray:
    """Prior std (SI) of each model parameter in ``names`` (``angles``: the model's angle parameters):
    default, then ``model.tolerances``, then
    ``priors``; each level's most specific selector wins. A selector that names no parameter of the model,
    or only parameters of another quantity than its unit, is an error (a typo must not go unnoticed)."""
    quantity = {n: quantity_of(n, angles) for n in names}
    std = {n: default_std(n, quantity[n]) for n in names}
    for level, specs in (("model file tolerances", list(getattr(model, "tolerances", ()) or ())),
                         ("prior", normalise(priors))):
        best: dict[str, tuple[int, float]] = {}
        for sel, value, q in specs:
            try:
                hit = model.select([sel])
            except KeyError as e:
                raise SolverInputError(f"{level} {sel!r}: {e.args[0]}") from None
            if q == "implied":  # {selector: std}: every parameter named must be of one quantity
                kinds = {quantity_of(n, angles) for n in hit}
                if len(kinds) > 1:
                    raise SolverInputError(f"{level} {sel!r}: it names lengths and angles; give the unit (e.g. "
                                           f"{sel}=0.3mm) or a (selector, std, quantity) triple")
                q = kinds.pop()
            same = [n for n in hit if q is None or quantity_of(n, angles) == q]
            if not same:
                raise SolverInputError(f"{level} {sel!r}: no {q} parameter in {sel!r} (check the unit)")
            for n in same:
                if n in std and (n not in best or len(same) < best[n][0]):
                    best[n] = (len(same), value)
        for n, (_, value) in best.items():
            std[n] = value
    return np.array([std[n] for n in names], dtype=float)
