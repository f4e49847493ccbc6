"""Where the web tests find the pages (a module of its own: ``conftest`` is a name every test directory has)."""
from __future__ import annotations

import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENGINE_WEB = ROOT / "rce" / "web"                                     # rce.js, the browser client, and echo.html
FLEET_WEB = ROOT / "examples" / "fleet" / "rce_fleet" / "live" / "web"  # the operator page (it imports ./rce.js)


def page_dir(where: Path) -> Path:
    """The operator page as a server serves it: the fleet's page files and the engine's rce.js in one
    directory (copies: a static route follows no links), for ``rce-master --static``; returns ``where``."""
    where.mkdir(parents=True, exist_ok=True)
    for f in [*FLEET_WEB.iterdir(), ENGINE_WEB / "rce.js"]:
        if f.is_file():
            shutil.copyfile(f, where / f.name)
    return where
