"""What every rce process shares: errors with codes (:mod:`.errors`), structured logs
(:mod:`.log`), kept tasks (:mod:`.tasks`), pending calls (:mod:`.pending`) and process
entry points (:mod:`.process`)."""
from rce.plumbing.errors import RCEError
from rce.plumbing.log import get_logger
from rce.plumbing.tasks import Tasks

__all__ = ["RCEError", "Tasks", "get_logger"]
