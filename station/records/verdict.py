"""PASS / FAIL / MARGINAL of one verdict measurement, the same for the records and the report."""

from __future__ import annotations

import math

STATUSES = ("PASS", "MARGINAL", "FAIL")


def finite_or_none(x) -> float | None:
    """``x`` as a finite float, else None (None, bools, text, NaN and infinities)."""
    if x is None or isinstance(x, bool):
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def measurement_status(m: dict) -> str:
    """A measurement ``{"name","value","unit","low","high","marginal","passed"}`` judged as the engine did.

    ``status`` wins when the engine wrote one. Otherwise ``passed`` (or, when absent, ``low <= value <= high``)
    decides PASS/FAIL, and a passing value is MARGINAL when ``marginal`` is ``True`` or a band width (in the
    measurement's unit) and the value lies within that band inside a limit."""
    status = str(m.get("status") or "").upper()
    if status in STATUSES:
        return status
    value, low, high = finite_or_none(m.get("value")), finite_or_none(m.get("low")), finite_or_none(m.get("high"))
    passed = m.get("passed")
    if passed is None:
        if value is None:
            return "FAIL"
        passed = (low is None or value >= low) and (high is None or value <= high)
    if not passed:
        return "FAIL"
    marginal = m.get("marginal")
    if marginal is True:
        return "MARGINAL"
    band = finite_or_none(marginal)
    if band and value is not None and (
            (high is not None and value > high - band) or (low is not None and value < low + band)):
        return "MARGINAL"
    return "PASS"


def overall_status(verdict: dict | None) -> str:
    """PASS, MARGINAL (passed with a marginal measurement), FAIL, NO LIMITS (nothing to judge against: never a
    pass), or NONE when there is no verdict."""
    if not verdict:
        return "NONE"
    if verdict.get("status") == "NO LIMITS":
        return "NO LIMITS"
    statuses = [measurement_status(m) for m in verdict.get("measurements") or []]
    if verdict.get("passed") is False or "FAIL" in statuses:
        return "FAIL"
    if verdict.get("passed") is None and not statuses:
        return "NONE"
    return "MARGINAL" if "MARGINAL" in statuses else "PASS"
