"""The two distributions (rce, and rce-fleet in examples/fleet) build as wheels from the tracked files
alone, with no warning from the build backend, and carry the data their processes read: the Test
package's nodes and services a container runs, the engine's and the fleet's web pages, the fleet's ROS
package; and no bytecode."""
from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

NEEDED = {
    "rce": ["rce/packages/Test/stringEcho.py", "rce/packages/Test/paramTest.py",
            "rce/packages/Test/srv/StringEcho.srv", "rce/web/rce.js", "rce/web/echo.html",
            "rce_master/cli.py", "rce_robot/cli.py", "rce_container/cli.py", "rce_client/rce_ros.py"],
    "rce_fleet": ["rce_fleet/live/web/index.html", "rce_fleet/live/web/fleet.js",
                  "rce_fleet/nodes/packages/fleet/global_planner", "rce_fleet/nodes/packages/fleet/move_client",
                  "rce_fleet/lifelong/epibt.py"],
}


def _tracked_copy(dest: Path) -> Path:
    """The repository's tracked files (a clean clone's tree, with no build or bytecode left over) in ``dest``."""
    names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, check=True, capture_output=True).stdout
    for name in filter(None, names.decode().split("\0")):
        src = ROOT / name
        if src.is_file():
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / name)
    return dest


def test_both_wheels_build_without_warnings_and_carry_their_data(tmp_path):
    tree = _tracked_copy(tmp_path / "tree")
    out = tmp_path / "wheels"
    done = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(out), ".", "examples/fleet"],
                          cwd=tree, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "BuildBackendWarning" not in done.stderr, done.stderr[-3000:]
    for dist, needed in NEEDED.items():
        (wheel,) = out.glob(f"{dist}-*.whl")
        names = set(zipfile.ZipFile(wheel).namelist())
        assert not [n for n in needed if n not in names], (dist, sorted(names))
        assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")], dist
        (meta,) = [n for n in names if n.endswith(".dist-info/METADATA")]
        assert "License-Expression: Apache-2.0" in zipfile.ZipFile(wheel).read(meta).decode(), dist
