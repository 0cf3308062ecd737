"""``dh_full`` keeps the tool only where the data need it (procedures/dh_full.py ``tool_needed``): the F-test of the
nested fits against scipy's F distribution, computed here independently from the residual sums."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from scipy.stats import f

from station.engine.procedure import load_procedure

dh_full = load_procedure("dh_full").module  # the shipped file, loaded as the engine loads it


def fit(sigma: float, dof: int, trusted: bool = True):
    return SimpleNamespace(noise={"fitted_m": sigma, "dof": dof}, trusted=trusted)


@pytest.mark.parametrize("sigma1", [9.0e-6, 9.8e-6, 9.99e-6, 5e-6])
def test_nested_fits_keep_the_tool_when_the_f_test_says_so(sigma1):
    n0, n1 = 200, 197  # the tool adds three unknowns
    rss0, rss1 = (10e-6) ** 2 * n0, sigma1 ** 2 * n1
    want = bool((rss0 - rss1) / 3 / (rss1 / n1) > f.ppf(0.999, 3, n1))
    assert want is (sigma1 < 9.7e-6)  # the cases straddle the critical value (F = 5.64 near 9.72 um)
    assert dh_full.tool_needed(fit(10e-6, n0), fit(sigma1, n1)) is want


def test_a_tool_that_displaced_link_lengths_is_kept_only_when_it_fits_significantly_better():
    # the solver named lengths the tool cannot be told from unidentifiable: no more unknowns with the tool than
    # without (measured on the arm6 example world: 0.618 mm per axis without the tool, 0.010 mm with it)
    assert dh_full.tool_needed(fit(618e-6, 191), fit(10e-6, 193)) is True
    assert dh_full.tool_needed(fit(10e-6, 191), fit(9.95e-6, 193)) is False  # smaller by chance: not kept
    assert dh_full.tool_needed(fit(10e-6, 191), fit(10.5e-6, 193)) is False


def test_an_untrusted_tool_fit_is_never_kept():
    assert dh_full.tool_needed(fit(618e-6, 191), fit(10e-6, 188, trusted=False)) is False
