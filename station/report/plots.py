"""The report's figures as base64 PNG (matplotlib Agg through ``Figure`` objects: no pyplot, no global
backend switch, safe in threads). Input is the report dict of ``content.build_report`` (SI); plots show mm/deg.

Margins are set in inches from what each figure holds (``_margins``), not by matplotlib's constrained layout:
that solver draws every figure twice and was half of a report's time (2.0 -> 1.2 s for the five figures)."""

from __future__ import annotations

import base64
import io
import math

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

BEFORE, AFTER, HOLDOUT, LIMIT = "#9aa5b1", "#1f6fb2", "#e08a1e", "#c0392b"
MAX_BARS = 200  # poses drawn as bars; more are drawn as markers (linear cost, readable at 100k samples)
CHAR_IN = 0.085  # width of a 10 pt DejaVu Sans character, in inches (tick labels of names)


def _margins(fig: Figure, left: float, bottom: float, top: float, right: float = 0.2, gap: float = 0.0) -> None:
    """Axes margins in inches (``gap``: between stacked axes) -> the figure's subplot parameters."""
    w, h = fig.get_size_inches()
    n = len(fig.axes)
    axes_h = max(h - top - bottom - gap * (n - 1), 0.1 * n) / max(n, 1)
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        hspace=gap / axes_h if n > 1 else None)


def _png(fig: Figure) -> str:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _mm(values) -> np.ndarray:
    return np.array([math.nan if v is None else float(v) * 1e3 for v in values], dtype=float)


def residual_per_pose(report: dict) -> str | None:
    pp = report["residuals"]["per_pose"]
    if not pp["before_m"]:
        return None
    b, a = _mm(pp["before_m"]), _mm(pp["after_m"])
    holdout = np.array([s == "holdout" for s in pp["set"]])
    x = np.arange(len(b))
    fig = Figure(figsize=(9, 3.4))
    ax = fig.add_subplot()
    _margins(fig, left=0.8, bottom=0.6, top=0.8)  # suptitle and the legend row above the axes
    if len(x) <= MAX_BARS:
        w = 0.4
        ax.bar(x - w / 2, b, w, color=BEFORE, label="before (nominal model)")
        ax.bar(x[~holdout] + w / 2, a[~holdout], w, color=AFTER, label="after (calibrated), fit poses")
        if holdout.any():
            ax.bar(x[holdout] + w / 2, a[holdout], w, color=HOLDOUT, label="after, held-out poses")
    else:  # one bar (a patch) per pose costs seconds per thousand: one marker line per series instead
        dots = {"ls": "none", "marker": ".", "ms": 2}
        ax.plot(x, b, color=BEFORE, label="before (nominal model)", **dots)
        ax.plot(x[~holdout], a[~holdout], color=AFTER, label="after (calibrated), fit poses", **dots)
        if holdout.any():
            ax.plot(x[holdout], a[holdout], color=HOLDOUT, label="after, held-out poses", **dots)
    pos = np.concatenate([b[np.isfinite(b) & (b > 0)], a[np.isfinite(a) & (a > 0)]])
    if pos.size and pos.max() / max(pos.min(), 1e-12) > 30:
        ax.set_yscale("log")  # before is often 10-100x after: a linear axis would hide the after bars
    ax.set_xlabel("pose (sample order)")
    ax.set_ylabel("tip error (mm)")
    fig.suptitle("Residual per pose, before and after calibration")
    seqs = report["residuals"]["per_pose"].get("seq") or []
    if len(seqs) == len(x) and len(x) <= 40:
        ax.set_xticks(x, [str(s) for s in seqs], fontsize=7)
        ax.set_xlabel("pose (sample seq)")
    ax.legend(fontsize=8, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=3, frameon=False)
    ax.grid(axis="y", alpha=0.3)
    return _png(fig)


def error_histogram(report: dict) -> str | None:
    pp = report["residuals"]["per_pose"]
    if not pp["before_m"]:
        return None
    b, a = _mm(pp["before_m"]), _mm(pp["after_m"])
    b, a = b[np.isfinite(b)], a[np.isfinite(a)]
    allv = np.concatenate([b, a])
    allv = allv[allv > 0]
    if allv.size == 0:
        return None
    lo, hi = allv.min() * 0.8, allv.max() * 1.25
    log = hi / lo > 30
    bins = np.geomspace(lo, hi, 30) if log else np.linspace(0, hi, 30)
    fig = Figure(figsize=(6, 3.2))
    ax = fig.add_subplot()
    _margins(fig, left=0.7, bottom=0.6, top=0.4)
    ax.hist(b, bins=bins, color=BEFORE, alpha=0.85, label=f"before (n={b.size})")
    ax.hist(a, bins=bins, color=AFTER, alpha=0.85, label=f"after (n={a.size})")
    if log:
        ax.set_xscale("log")
    ax.set_xlabel("tip error (mm)")
    ax.set_ylabel("poses")
    ax.set_title("Error histogram")
    ax.legend(fontsize=8)
    return _png(fig)


def corrections(report: dict) -> str | None:
    rows = [p for p in report["parameters"] if p["identifiable"] and p["kind"] == "model"
            and p["correction"] is not None]
    if not rows:
        return None
    groups = [("rad", "deg", math.degrees, "angle correction (deg)"), ("m", "mm", lambda v: v * 1e3,
                                                                       "length correction (mm)")]
    groups = [(u, hu, f, t, [p for p in rows if p["unit"] == u]) for u, hu, f, t in groups]
    groups = [g for g in groups if g[4]]
    height = 1.0 + 0.32 * sum(len(g[4]) for g in groups) + 0.6 * len(groups)
    fig = Figure(figsize=(8, max(2.4, height) + 0.4))
    axes = fig.subplots(len(groups), 1, squeeze=False,
                        gridspec_kw={"height_ratios": [len(g[4]) + 1 for g in groups]})[:, 0]
    longest = max(len(p["name"]) for g in groups for p in g[4])
    _margins(fig, left=0.3 + CHAR_IN * longest, bottom=0.6, top=0.4, gap=0.75)  # gap: the upper x label
    for ax, (_, _, conv, title, ps) in zip(axes, groups, strict=True):
        y = np.arange(len(ps))
        vals = np.array([conv(p["correction"]) for p in ps])
        err = np.array([2 * conv(p["std"]) if p["std"] is not None else 0.0 for p in ps])
        ax.errorbar(vals, y, xerr=err, fmt="o", color=AFTER, ecolor="#333", capsize=4)
        ax.axvline(0, color="#888", lw=0.8)
        ax.set_yticks(y, [p["name"] for p in ps])
        ax.invert_yaxis()
        ax.set_xlabel(title + "  ±2σ")
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_title("Parameter corrections (estimate − nominal) with 95 % error bars")
    return _png(fig)


def coverage_joints(report: dict) -> str | None:
    joints = report["coverage"]["joints"]
    if not joints:
        return None
    fig = Figure(figsize=(8, 0.55 * len(joints) + 1.2))
    ax = fig.add_subplot()
    _margins(fig, left=0.3 + CHAR_IN * max(len(str(j["joint"])) for j in joints), bottom=0.4, top=0.4)
    for i, j in enumerate(joints):
        conv = math.degrees if j["kind"] == "revolute" else (lambda v: v * 1e3)
        if j["lower"] is not None:
            lo, hi = conv(j["lower"]), conv(j["upper"])
            # limits normalised to [0, 1] so every joint reads on one axis
            ax.barh(i, 1.0, left=0.0, color="#e6eaee", edgecolor="#b8c0c8")
            a, b = (conv(j["min"]) - lo) / (hi - lo), (conv(j["max"]) - lo) / (hi - lo)
            ax.barh(i, b - a, left=a, color=AFTER, alpha=0.55, height=0.5)
            ax.text(1.01, i, f"{j['fraction'] * 100:4.0f} % of [{lo:.0f}, {hi:.0f}] "
                    f"{'deg' if j['kind'] == 'revolute' else 'mm'}", va="center", fontsize=8)
        else:
            ax.text(0.0, i, f"used {conv(j['min']):.1f} .. {conv(j['max']):.1f} (limits unknown)", va="center",
                    fontsize=8)
    ax.set_yticks(range(len(joints)), [j["joint"] for j in joints])
    ax.set_xlim(0, 1.45)
    ax.set_xticks([0, 0.25, 0.5, 0.75, 1.0], ["lower", "", "middle", "", "upper"])
    ax.invert_yaxis()
    ax.set_title("Joint-space coverage: range used by the poses within each joint's limits")
    return _png(fig)


def coverage_tool(report: dict) -> str | None:
    tool = report["coverage"].get("tool")
    if not tool:
        return None
    fig = Figure(figsize=(4.2, 4.2))
    ax = fig.add_subplot(projection="polar")
    _margins(fig, left=0.4, bottom=0.3, top=0.75, right=0.4)  # a two-line title
    az, tilt = np.radians(tool["azimuth_deg"]), np.array(tool["tilt_deg"])
    ax.scatter(az, tilt, color=AFTER, s=22)
    top = max(30.0, float(np.nanmax(tilt)) * 1.1 if tilt.size else 30.0)
    ax.set_rlim(0, top)
    ax.set_rticks(np.linspace(0, top, 4)[1:].round())
    ax.set_rlabel_position(200)
    ax.set_title(f"Tool axis directions (tilt from straight down, deg)\n"
                 f"spread: {tool['max_pairwise_deg']:.0f}° between the farthest two", fontsize=9)
    return _png(fig)


def all_plots(report: dict) -> dict[str, str | None]:
    return {"residual_per_pose": residual_per_pose(report), "error_histogram": error_histogram(report),
            "corrections": corrections(report), "coverage_joints": coverage_joints(report),
            "coverage_tool": coverage_tool(report)}
