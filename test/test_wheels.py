"""Built wheels work without the checkout: `lsu doctor` and `lsu launch selftest` from a scratch venv.

The Python packages are built as wheels (`pip wheel --no-deps`, offline: the build uses this
venv's setuptools) and installed into a new venv that sees this venv's site-packages (ROS
wheels, numpy, lsu_interfaces) through a ``.pth`` line. Such a line adds the folder to
``sys.path`` without running the ``.pth`` files in it, so the editable installs of the
checkout stay out of the scratch venv: what runs is the wheels' code and the configuration
they carry. Both commands run from a folder outside the checkout.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
import yaml

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.name for p in (ROOT / "src").iterdir() if (p / "setup.py").is_file())


def run(cmd, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kw)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    """A venv with the wheels of every Python package installed (not editable)."""
    tmp = tmp_path_factory.mktemp("wheels")
    built = run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q",
                 "-w", str(tmp / "dist"), *(str(ROOT / "src" / p) for p in PACKAGES)], cwd=tmp)
    assert built.returncode == 0, built.stderr[-3000:]
    wheels = sorted((tmp / "dist").glob("*.whl"))
    assert {w.name.split("-")[0] for w in wheels} == set(PACKAGES)
    venv = tmp / "venv"
    made = run([sys.executable, "-m", "venv", "--without-pip", str(venv)])
    assert made.returncode == 0, made.stderr
    python = venv / "bin" / "python"
    site = Path(run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]).stdout.strip())
    (site / "lsu_base_venv.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    installed = run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "-q",
                     *map(str, wheels)], cwd=tmp)
    assert installed.returncode == 0, installed.stderr[-3000:]
    return venv


def scratch_env(venv: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("LSU_", "PYTHON"))}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    env["VIRTUAL_ENV"] = str(venv)
    return env


def test_wheels_run_doctor_and_selftest_outside_the_checkout(scratch, tmp_path):
    env, lsu = scratch_env(scratch), str(scratch / "bin" / "lsu")
    where = run([str(scratch / "bin" / "python"), "-c",
                 "import lsu_tools, lsu_config; from lsu_tools.nodes_index import resolve_executable as r; "
                 "print(lsu_tools.__file__, lsu_config.config_dir(), r('lsu_tools', 'selftest_talker'))"],
                cwd=tmp_path, env=env)
    assert where.returncode == 0, where.stderr
    module, config, talker = map(Path, where.stdout.split())
    for path in (module, config, talker):  # the wheels' code, data and scripts, not the checkout's
        assert path.is_relative_to(scratch), path
    assert (Path(config) / "launch" / "selftest.launch.yaml").is_file()

    doctor = run([lsu, "doctor"], cwd=tmp_path, env=env)
    assert doctor.returncode == 0 and "lsu doctor: all checks passed" in doctor.stdout, doctor.stdout + doctor.stderr
    assert re.search(rf"^OK\s+python\s.* at {re.escape(str(scratch))}/bin/python$", doctor.stdout, re.M), doctor.stdout
    assert re.search(r"^OK\s+interfaces\s", doctor.stdout, re.M), doctor.stdout

    launch = subprocess.Popen([lsu, "launch", "selftest", "namespace:=wheel"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        echo = run([lsu, "topic", "echo", "/wheel/selftest/echo", "--once", "--timeout", "30"], cwd=tmp_path, env=env)
        assert echo.returncode == 0, echo.stderr
        msg = yaml.safe_load(echo.stdout.split("---")[0])
        assert msg["firmware"] == "selftest" and re.fullmatch(r"echo \d+", msg["fault"])  # talker -> listener
    finally:
        os.killpg(launch.pid, signal.SIGINT)
        try:
            out, _ = launch.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(launch.pid, signal.SIGKILL)
            out, _ = launch.communicate()
    assert launch.returncode == 0, out[-3000:]
    assert re.search(r"started \S+ \(lsu_tools/selftest_talker\) pid \d+", out), out[-3000:]
