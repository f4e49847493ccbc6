"""The master's admin token (its clients find it with :func:`rce.tools.admin_client.find_token`)."""
from __future__ import annotations

import os
import secrets
from pathlib import Path

from rce.tools.admin_client import TOKEN_ENV, token_file
from rce.plumbing.process import create_private_file


def load_or_create(path: Path | None) -> str:
    """``RCE_ADMIN_TOKEN`` if set, else the token in ``path`` (default
    :func:`~rce.tools.admin_client.token_file`), created with mode 0600 if missing."""
    env = os.environ.get(TOKEN_ENV)
    if env:
        return env
    path = path or token_file()
    if not path.exists():
        create_private_file(path, secrets.token_urlsafe(24) + "\n")
    return path.read_text().strip()
