# Fleet tests. ``rce_fleet`` lives in examples/fleet; make it importable even when the
# editable install does not map it (pyproject's package-dir maps it for wheel builds).
import sys
from pathlib import Path

try:
    import rce_fleet  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples" / "fleet"))
