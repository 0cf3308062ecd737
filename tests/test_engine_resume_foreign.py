"""`station resume` on a session that has no procedure file (a crashed jog session) is a one-line error."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from station.robot import Identity
from station.tui.session import JogSession, session_header

STATION = str(Path(sys.executable).with_name("station"))


def test_resume_of_a_crashed_jog_session_is_a_one_line_error(tmp_path):
    ident = Identity(vendor="ROBOTIS", model="omx", serial="OMX-1")
    header = session_header(identity=ident, model_name="omx", serial="OMX-1", identify="offsets",
                            reference="unknown", url="dynamixel:///dev/null?ids=11-14&model=omx")
    s = JogSession.create(header=header, joint_units=["rad"] * 4, folder=tmp_path / "jog")
    s.add_sample(np.zeros(4), "A", raw=(2048,) * 4, raw_unit="tick", t=0.0, t_device=None,
                 touch=True, status={"enabled": True})
    # no close(): the station crashed while the technician was jogging
    p = subprocess.run([STATION, "resume", str(tmp_path / "jog")], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("station: error:"), p.stderr
    assert "no procedure file to resume" in lines[0]
    assert (tmp_path / "jog" / "journal.jsonl").read_text().count('"type":"sample"') == 1  # nothing lost
