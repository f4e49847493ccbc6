"""The users file (``rce-master --users PATH``, ``rce-console user add --file PATH``): JSON
``{"users": [record, ...]}`` with the hashed records of :class:`~rce_master.model.User`
(never a clear password), mode 0600, replaced atomically on every change."""
from __future__ import annotations

import json
import os
from pathlib import Path

from rce.errors import RequestError
from rce_master.state import MasterState


class UsersFile:
    """The users file at ``path`` (absent: no users)."""

    def __init__(self, path: Path):
        self.path = Path(path)

    def load(self, state: MasterState) -> None:
        """Add the file's users to ``state``. Raises :class:`RequestError` naming the file."""
        try:
            records = json.loads(self.path.read_text()).get("users", []) if self.path.exists() else []
            state.load_users(records)
        except (OSError, ValueError, AttributeError, RequestError) as e:
            raise RequestError(f"{self.path}: cannot load users: {e}") from None

    def save(self, state: MasterState) -> None:
        """Write the users of ``state`` (a temporary file, then renamed over the old one)."""
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"users": state.user_records()}, indent=1))
        os.chmod(tmp, 0o600)
        tmp.replace(self.path)
