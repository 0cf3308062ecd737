"""The HTML report in a real browser: headless Debian chromium loads it from file:// with networking off,
decodes every embedded plot, and renders the verdict colours (CSS applied). .ci/run installs chromium."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

from station.report import write_report

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars"]


@pytest.fixture(scope="module")
def chromium() -> str:
    exe = shutil.which("chromium") or ("/usr/bin/chromium" if os.path.exists("/usr/bin/chromium") else None)
    if exe is None:
        pytest.fail("the report browser test needs Debian's chromium (apt-get install -y chromium; .ci/run does)",
                    pytrace=False)
    return exe


def _run(chromium: str, profile: Path, *args: str, timeout: float = 90) -> str:
    """Run chromium in its own process group and make sure no helper process outlives the call."""
    proc = subprocess.Popen([chromium, *FLAGS, f"--user-data-dir={profile}", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail(f"chromium did not finish within {timeout} s")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-2000:]
    return out


@pytest.fixture(scope="module")
def report(session_factory, tmp_path_factory) -> Path:
    session, _ = session_factory(seed=12)
    return write_report(session, tmp_path_factory.mktemp("browser"))


def test_browser_decodes_every_plot(chromium, report, tmp_path):
    # a probe copy: the same page plus one inline script that writes what the browser loaded into the DOM;
    # the CSP still allows images from data: URIs only, so an external image would have size 0
    html = report.read_text()
    csp = "default-src 'none'; img-src data:; style-src 'unsafe-inline'"
    assert csp in html
    probe = html.replace(csp, csp + "; script-src 'unsafe-inline'").replace("</body>", """<script>
window.addEventListener('load', () => {
  const d = document.createElement('pre'); d.id = 'probe';
  const imgs = [...document.images].map(i => i.complete + ':' + i.naturalWidth + 'x' + i.naturalHeight);
  const st = [...document.querySelectorAll('td.st')].map(td => getComputedStyle(td).backgroundColor);
  d.textContent = JSON.stringify({imgs: imgs, status: st, title: document.title});
  document.body.appendChild(d);
});
</script></body>""")
    page = tmp_path / "probe.html"
    page.write_text(probe)
    dom = _run(chromium, tmp_path / "profile", "--virtual-time-budget=10000", "--dump-dom", page.as_uri())
    m = re.search(r'<pre id="probe">(.*?)</pre>', dom, re.S)
    assert m, dom[-1000:]
    got = json.loads(m.group(1).replace("&quot;", '"'))
    assert len(got["imgs"]) == 5
    for entry in got["imgs"]:
        complete, size = entry.split(":")
        w, h = (int(v) for v in size.split("x"))
        assert complete == "true" and w > 300 and h > 200, got["imgs"]
    assert got["status"] and all(c == "rgb(30, 132, 73)" for c in got["status"])  # green PASS cells
    assert "Calibration report" in got["title"]
    assert "Unidentifiable parameters" in dom and "offset.j6" in dom


def test_screenshot_reads(chromium, report, tmp_path):
    """The untouched report as a person sees it: the page is drawn, the PASS banner is green, plots appear."""
    import matplotlib.image as mpimg

    shot = tmp_path / "report.png"
    _run(chromium, tmp_path / "profile", "--window-size=1100,2600", f"--screenshot={shot}", report.as_uri())
    img = mpimg.imread(shot)[..., :3]
    assert img.shape[:2] == (2600, 1100)
    top = img[:200]
    green = np.all(np.abs(top - np.array([30, 132, 73]) / 255) < 0.03, axis=-1)
    assert green.sum() > 1000  # the banner
    # plots: many distinct colours in the lower part (text alone is black/grey on white)
    lower = (img[1000:] * 255).astype(int)
    colours = {tuple(c) for c in lower.reshape(-1, 3)[::37]}
    assert len(colours) > 200
    assert np.mean(np.all(lower > 245, axis=-1)) < 0.97  # not blank
