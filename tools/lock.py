"""Resolve requirements.in into requirements.lock (every distribution pinned with ==).

The pins already in requirements.lock are kept (given to pip as constraints), so adding a
dependency does not move the versions the suite and the benchmarks were measured with;
`--upgrade` resolves every distribution afresh.

Uses pip's own resolver (`pip install --dry-run --report`), so the lock holds exactly what
pip would install on a bare machine - not `pip freeze`, which also lists metadata that the
ROS wheels vendor and that cannot be installed on its own.
"""

import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEADER = """# Pinned environment of the LSU workspace: what `make setup` installs.
# Direct dependencies are listed in requirements.in; this file pins the whole resolved set.
# Regenerate after editing requirements.in: make lock
"""


def main() -> int:
    lock = ROOT / "requirements.lock"
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "report.json"
        keep: list[str] = []
        if "--upgrade" not in sys.argv[1:] and lock.is_file():
            keep = ["-c", str(lock)]
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--dry-run", "--ignore-installed",
                        "--report", str(report), "-r", str(ROOT / "requirements.in"), *keep], check=True)
        installs = json.loads(report.read_text())["install"]
    pins = sorted((i["metadata"]["name"], i["metadata"]["version"]) for i in installs)
    body = "".join(f"{name}=={version}\n" for name, version in sorted(pins, key=lambda p: p[0].lower()))
    lock.write_text(HEADER + body)
    print(f"requirements.lock: {len(pins)} pinned distributions")
    return 0


if __name__ == "__main__":
    sys.exit(main())
