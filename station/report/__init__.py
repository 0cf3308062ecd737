"""Calibration reports: a self-contained HTML page (matplotlib plots embedded as PNG) and a JSON twin (SI).

``write_report(session, folder) -> Path`` takes the plain session record dict of docs/architecture.md."""

from station.report.content import FORMAT, ReportError, build_report
from station.report.render import render_html, write_report

__all__ = ["FORMAT", "ReportError", "build_report", "render_html", "write_report"]
