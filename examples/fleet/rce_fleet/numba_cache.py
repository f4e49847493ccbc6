"""numba's cache (``cache=True``) for fleet nodes in a sandbox, prepared in the tree.

numba keeps a module's compiled kernels next to its source (``__pycache__``) when it can write
there, else in the user-wide cache (``$HOME/.cache/numba``). A fleet node in a sandbox can use
neither: the tree is another user's, and its HOME is its container's own, new with every
container; so each container compiled every kernel again (1 - 2.5 s of CPU for SIPP alone).

``make bytecode`` compiles the kernels into the tree (:mod:`rce_fleet.compile_kernels`, run as
the tree's owner), and each module with kernels calls :func:`seed` before it defines them: when the
tree's cache cannot be written by this process but has entries for that module, they are
copied into the user-wide cache numba falls back to, which it then loads from, checking them
as any cache entry (source hash, numba version, CPU; a stale entry is compiled again and
replaced there). The copies come from the tree, as the source does: no user's node writes
anything another user's node loads.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from numba import config
from numba.core.caching import UserWideCacheLocator

#: numba's cache files: an index and the compiled data of each signature.
CACHE_SUFFIXES = (".nbi", ".nbc")


def seed(py_file: str) -> None:
    """Before a module at ``py_file`` defines its ``cache=True`` kernels: copy the tree's cache
    entries for it into the user-wide cache when this process cannot write the tree's (see the
    module doc). Entries already there are kept; an :class:`OSError` leaves numba to compile."""
    tree = Path(py_file).resolve().parent / "__pycache__"
    if config.CACHE_DIR or not tree.is_dir() or os.access(tree, os.W_OK):
        return                        # numba uses $NUMBA_CACHE_DIR or the tree itself
    stem = Path(py_file).stem + "."
    entries = [f for f in tree.iterdir() if f.name.startswith(stem) and f.suffix in CACHE_SUFFIXES]
    locator = UserWideCacheLocator.from_function(seed, str(Path(py_file).resolve()))   # None if not writable
    if not entries or locator is None:
        return
    dest = Path(locator.get_cache_path())
    try:
        for f in entries:
            if not (dest / f.name).exists():
                fd, tmp = tempfile.mkstemp(dir=dest, prefix=".seed-")
                with os.fdopen(fd, "wb") as out, open(f, "rb") as src:
                    shutil.copyfileobj(src, out)
                os.replace(tmp, dest / f.name)     # whole or not at all, for a concurrent reader
    except OSError:
        return
