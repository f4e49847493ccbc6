"""The users: the users file (``rce-master --users PATH``, ``rce-console user add --file PATH``):
JSON ``{"users": [record, ...]}`` with the hashed records of :class:`~rce_master.state.model.User`
(never a clear password), mode 0600, replaced atomically on every change; and the one password
check of a login (:func:`verify`), which costs the same for a user that does not exist."""
from __future__ import annotations

import json
import os
from pathlib import Path

from rce.plumbing.errors import RequestError
from rce_master.state.model import User, password_digest
from rce_master.state.master_state import MasterState

# a user no one can log in as (a random salt and key: no digest's scrypt matches it), whose scrypt an
# unknown user name costs: an unknown user and a wrong password take the same time (docs/SECURITY.md)
_NOBODY = User("", os.urandom(16), os.urandom(32))


def verify(users: dict[str, User], name: str, digest_hex: str) -> bool:
    """True if ``digest_hex`` (the hex SHA-256 of the password, docs/design.md, section 3.2) is the password
    of user ``name`` in ``users``. Runs one scrypt (RFC 7914; ~50 ms of CPU, and releases the GIL)
    whether the user exists or not, so that the time taken does not tell which. Blocking: run it
    off the event loop (:class:`~rce_master.auth.login_guard.PasswordCheck` does)."""
    user = users.get(name)
    digest = digest_hex if isinstance(digest_hex, str) else password_digest("")
    ok = (user or _NOBODY).check(digest)
    return ok and user is not None


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
