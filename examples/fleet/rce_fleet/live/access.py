"""Who logs in to ``rce-fleet demo``/``serve``: the fleet's own internal user, and the people.

- **The fleet's internal user** (:data:`INTERNAL_USER`) owns the fleet container; the fleet manager, the
  robots, the page's and Foxglove's sessions to the container, the recorders run as it. Its password is
  drawn at random for each run (:func:`secrets.token_urlsafe`, 192 bits), kept in memory and in the robots'
  configs in the work directory (mode 0600, in a 0700 directory), and never printed. It is never a person's
  login: the page, the task API and the Foxglove port refuse it as they refuse a wrong password.
- **People** log in with the master's users and their roles (docs/task-api.md): the records of ``--users
  FILE`` (read, never written: the master keeps its own copy, ``engine/users.json`` in the work directory),
  and a first admin, :data:`FIRST_ADMIN`, whose password is the first line of ``--admin-password-file
  FILE``. With neither on a page that listens on loopback alone, the first admin's password is made for the
  run and written to ``admin-password`` in the work directory (mode 0600); its path is printed, never the
  password. A page that listens beyond loopback without either is refused at start, naming the flags, as
  is a users file that holds the well-known ``testUser``/``testUser`` of ``rce-master --dev``: such a serve
  has no well-known login.

The master runs ``--dev --no-dev-user --users engine/users.json``: no ``testUser`` there either.
"""
from __future__ import annotations

import ipaddress
import json
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

from .options import UsageError, WebAccess

__all__ = ["FIRST_ADMIN", "INTERNAL_USER", "Access", "is_loopback", "prepare_access"]

INTERNAL_USER = "fleet-internal"      # the fleet's own user: owns the fleet container; no person's login
FIRST_ADMIN = "admin"                 # the first admin's name (--admin-password-file, or the made password)
ADMIN_PASSWORD_FILE = "admin-password"   # in the work directory, 0600: the made password of a loopback run
MIN_PASSWORD = 8                      # characters a first admin's password has at least
WELL_KNOWN = ("testUser", "testUser")  # rce-master --dev's user and password


def is_loopback(bind: str) -> bool:
    """Whether ``bind`` (an address or ``localhost``) listens on loopback alone (127.0.0.0/8, ::1)."""
    if bind == "localhost":
        return True
    try:
        return ipaddress.ip_address(bind.strip("[]")).is_loopback
    except ValueError:
        return False       # a host name: whatever it resolves to may be reachable


@dataclass
class Access:
    """What a run logs in with: the internal user's name and password, the master's users file
    (``users_file``), what the banner says about the first admin (``admin_note``: never a password) and the
    user the page prefills (``admin_user``: the first admin, or none)."""
    user: str
    password: str
    users_file: Path
    admin_note: str
    admin_user: str = ""


def _records(path: str | None) -> list[dict]:
    if path is None:
        return []
    try:
        records = json.loads(Path(path).read_text()).get("users", [])
        if not isinstance(records, list) or not all(isinstance(r, dict) and "name" in r for r in records):
            raise ValueError("'users' must be a list of records with a name")
    except (OSError, ValueError, AttributeError) as e:
        raise UsageError(f"--users {path}: not a users file (rce-console user add --file): {e}") from None
    return records


def _admin_password(path: str) -> str:
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise UsageError(f"--admin-password-file {path}: cannot read it: {e.strerror}") from None
    pw = lines[0].strip() if lines else ""
    if len(pw) < MIN_PASSWORD:
        raise UsageError(f"--admin-password-file {path}: its first line must be a password of at least "
                         f"{MIN_PASSWORD} characters")
    return pw


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)


def prepare_access(web: WebAccess, workdir: Path, *, page: bool) -> Access:
    """The internal user and the master's users file (written to ``workdir/engine/users.json``, 0600) for a
    run whose page (``page``: served at all) listens on ``web.bind``. Raises :class:`UsageError` naming
    the fix for a page beyond loopback without a first admin, a well-known login, or a clash of names."""
    from rce_master.state.model import User
    records = _records(web.users)
    names = {r["name"] for r in records}
    if INTERNAL_USER in names:
        raise UsageError(f"--users {web.users}: user {INTERNAL_USER!r} is the name rce-fleet keeps for its own "
                         "internal user; give that person another name")
    beyond = page and not is_loopback(web.bind)
    if beyond:
        for r in records:
            if r["name"] == WELL_KNOWN[0] and User.from_record(r).check(_digest(WELL_KNOWN[1])):
                raise UsageError(f"--users {web.users}: {WELL_KNOWN[0]} has the well-known password of "
                                 f"rce-master --dev; with --web-bind {web.bind} set another (rce-console user "
                                 f"passwd) or remove it")
    admin_pw, note = None, ""
    if web.admin_password_file:
        if FIRST_ADMIN in names:
            raise UsageError(f"--admin-password-file: --users {web.users} has a user {FIRST_ADMIN!r} already; "
                             "give one or the other")
        admin_pw = _admin_password(web.admin_password_file)
        note = f"log in as {FIRST_ADMIN} with the password of {web.admin_password_file}"
    elif beyond and not any(r.get("role") == "admin" for r in records):
        raise UsageError(f"--web-bind {web.bind} listens beyond loopback and this serve would have no admin of "
                         f"yours: give the first admin's password with --admin-password-file FILE (user "
                         f"{FIRST_ADMIN}), or --users FILE with an admin (rce-console user add NAME --role admin "
                         "--file FILE)")
    elif not records and page:
        admin_pw = secrets.token_urlsafe(12)
        made = workdir / ADMIN_PASSWORD_FILE
        _write_private(made, admin_pw + "\n")
        note = f"log in as {FIRST_ADMIN}; the password is in {made}"
    elif records:
        note = f"log in with a user of {web.users}"
    password = secrets.token_urlsafe(24)
    users = [User.create(INTERNAL_USER, password, "viewer").to_record(), *records]
    if admin_pw is not None:
        users.append(User.create(FIRST_ADMIN, admin_pw, "admin").to_record())
    engine = workdir / "engine"
    engine.mkdir(parents=True, exist_ok=True)
    _write_private(engine / "users.json", json.dumps({"users": users}, indent=1))
    return Access(INTERNAL_USER, password, engine / "users.json", note, FIRST_ADMIN if admin_pw else "")


def _digest(password: str) -> str:
    from rce_master.state.model import password_digest
    return password_digest(password)
