"""``station.cli.opcua_cmd``: ``station opcua`` refuses bad input in one line before any server starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from station.cli.opcua_cmd import opcua
from station.robot.errors import ConfigError


def run(tmp_path, **kw):
    args = dict(robot="ur://127.0.0.1:9", cell=tmp_path / "absent.yaml", endpoint="opc.tcp://127.0.0.1:4840",
                procedure="zero_offsets", limits=None, db=None, reference=None, poses=None, holdout=None, cone=None,
                cert=None, key=None, trust=None, users=None)
    args.update(kw)
    opcua(**args)


def test_off_loopback_without_a_certificate_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="is not loopback: it is served only with Basic256Sha256"):
        run(tmp_path, endpoint="opc.tcp://0.0.0.0:4840")


def test_a_missing_cell_or_procedure_is_named_before_serving(tmp_path):
    with pytest.raises(ConfigError) as e:
        run(tmp_path)
    assert "absent.yaml" in str(e.value)
    cell = tmp_path / "cell.yaml"
    cell.write_text("format: station-cell/1\nunits: {length: mm}\npoints:\n"
                    "  A: {kind: socket, position: [350, 0, 750], approach: [0, 0, 1]}\n")
    with pytest.raises(Exception, match="no_such_procedure"):
        run(tmp_path, cell=Path(cell), procedure="no_such_procedure")
