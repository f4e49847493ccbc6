"""Where the fleet's node package (``pkg: fleet``: global_planner, move_client) is installed.

Registered as the ``rce.packages`` entry point ``fleet`` so container hosts find it
without ``RCE_PACKAGE_PATH``."""
from pathlib import Path

PACKAGE_DIR = str(Path(__file__).parent / "packages" / "fleet")
