"""The admin token shared by rce-master and its tools (rce-console, rce-topic --container)."""
from __future__ import annotations

import os
import secrets
from pathlib import Path

DEFAULT_TOKEN_FILE = Path(os.environ.get("XDG_CONFIG_HOME", Path.home() / ".config")) / "rce" / "admin-token"


def load_or_create(path: Path | None) -> str:
    """``RCE_ADMIN_TOKEN`` if set, else the token in ``path`` (created with mode 0600 if missing)."""
    env = os.environ.get("RCE_ADMIN_TOKEN")
    if env:
        return env
    path = path or DEFAULT_TOKEN_FILE
    if path.exists():
        return path.read_text().strip()
    path.parent.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(24)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    return token


def read(path: Path | None = None) -> str | None:
    """The token for a client: ``RCE_ADMIN_TOKEN``, else the token file, else None."""
    env = os.environ.get("RCE_ADMIN_TOKEN")
    if env:
        return env
    path = path or DEFAULT_TOKEN_FILE
    return path.read_text().strip() if path.exists() else None
