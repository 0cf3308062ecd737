"""Installable: a wheel built from the project, installed into a fresh virtual environment (no system site
packages, no source tree on the path; the dependencies are the project environment's), finds its shipped
procedures, default limits and built-in models as package data and runs ``station demo --robot canopen`` to
PASS."""

import os
import shutil
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SKIP = {".venv", "build", "dist", ".git", "__pycache__", ".pytest_cache", ".ruff_cache", "station-data"}

pytestmark = pytest.mark.slow


def _copy_source(dest: Path) -> Path:
    """The project without build leftovers (a stale build/ would leak old files into the wheel)."""
    def ignore(folder, names):
        return [n for n in names if n in SKIP or n.endswith(".egg-info")]

    shutil.copytree(ROOT, dest, ignore=ignore)
    return dest


def _run(cmd, **kw):
    out = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert out.returncode == 0, f"{' '.join(map(str, cmd))}\n{out.stdout[-2000:]}\n{out.stderr[-3000:]}"
    return out


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    src = _copy_source(tmp / "src")
    _run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-w", str(tmp / "dist"), "-q",
          "--disable-pip-version-check"], timeout=600)
    wheel = next((tmp / "dist").glob("station-*.whl"))
    env_dir = tmp / "venv"
    venv.EnvBuilder(with_pip=True, system_site_packages=False).create(env_dir)
    py = env_dir / "bin" / "python"
    # The wheel goes in alone; its dependencies are the ones `make venv` installed from the same pyproject
    # (copying numpy/scipy/... into a second environment took ~55 s of the suite's budget). The project
    # environment's site-packages is appended to the path by a .pth file: the wheel's `station` comes first, and
    # the project's editable install stays inert (.pth files are run only in site directories: its finder is
    # never installed), which the checks below confirm (station and its data load from the new environment).
    _run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-compile", "--disable-pip-version-check",
          str(wheel)], timeout=300)
    deps = dict.fromkeys(sysconfig.get_paths()[k] for k in ("purelib", "platlib"))  # this (project) venv's
    site = next((env_dir / "lib").glob("python3*/site-packages"))
    (site / "zz-project-dependencies.pth").write_text("".join(f"{d}\n" for d in deps))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "STATION_HOME", "STATION_DB",
                                                           "STATION_CELL", "VIRTUAL_ENV")}
    work = tmp / "work"  # neither the source tree nor the project's venv is anywhere on the path
    work.mkdir()
    return env_dir, {**env, "STATION_HOME": str(work / "home")}, work


def test_shipped_procedures_and_limits_are_package_data(installed):
    env_dir, env, work = installed
    code = ("import station, station.engine.procedure as p\n"
            "from station.engine import load_limits, load_procedure, shipped_names\n"
            "from station.kinematics import load_model\n"
            "print(station.__file__)\n"
            "print(','.join(shipped_names()))\n"
            "print(load_procedure('zero_offsets').path)\n"
            "print(load_limits().path)\n"
            "print(load_model('arm6').n_joints)\n")
    out = _run([str(env_dir / "bin" / "python"), "-c", code], env=env, cwd=work, timeout=120)
    pkg, names, proc, limits, joints = out.stdout.split()
    site = str(env_dir)
    assert pkg.startswith(site) and not pkg.startswith(str(ROOT))
    assert set(names.split(",")) >= {"zero_offsets", "tcp_4point", "tcp_circle", "dh_full", "verify"}
    assert proc.startswith(site) and proc.endswith("zero_offsets.py")
    assert limits.startswith(site) and limits.endswith("limits.yaml")
    assert joints == "6"


def test_demo_runs_from_the_installed_wheel(installed):
    env_dir, env, work = installed
    out = subprocess.run([str(env_dir / "bin" / "station"), "demo", "--robot", "canopen"], env=env, cwd=work,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "PASS"
    sessions = list((work / "home" / "sessions").glob("zero_offsets-*/journal.jsonl"))
    assert len(sessions) == 1 and (sessions[0].parent / "report.html").is_file()
