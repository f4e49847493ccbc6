"""Fleet nodes in a sandbox load the numba kernels compiled into the tree (``make bytecode``,
rce_fleet.compile_kernels) instead of compiling them in every container
(rce_fleet.numba_cache): a real node, forked by a real zygote in the namespaced sandbox (its
container's uid, which cannot write the tree, and its container's HOME) and in the unconfined
one (the tree's own user)."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from rce_fleet import compile_kernels
from tests.container.test_zygote import box, wait_logs  # noqa: F401 -- box: a sandbox, its template and launchers

pytestmark = pytest.mark.asyncio

#: A node that runs the SIPP kernel once and says whether numba compiled it or loaded it.
KERNELS = (
    "import json, os\n"
    "from rce_fleet.planning import sipp_kernel\n"
    "sipp_kernel.warm_up()\n"
    "stats = sipp_kernel.sipp_search.stats\n"
    "cache = os.path.join(os.environ['HOME'], '.cache', 'numba')\n"
    "print(json.dumps({'hits': sum(stats.cache_hits.values()), 'misses': sum(stats.cache_misses.values()),\n"
    "                  'uid': os.getuid(), 'copies': sorted(f for _, _, fs in os.walk(cache) for f in fs)}),\n"
    "      flush=True)\n")


async def test_a_sandboxed_fleet_node_loads_the_kernels_from_the_trees_cache(box):  # noqa: F811
    compile_kernels.main()                       # what make bytecode does (a load when the tree's cache is current)
    (Path(os.environ["RCE_PACKAGE_PATH"]) / "ZTest" / "kernels.py").write_text(KERNELS)
    lc = box.launcher()
    try:
        await lc.add({"ntag": "kernels", "pkg": "ZTest", "exe": "kernels.py"})
        seen = json.loads((await wait_logs(lc, "kernels"))[0])
    finally:
        await lc.close()
    assert seen["misses"] == 0 and seen["hits"] >= 1, seen
    if box.sandbox.node_uid is not None:         # the tree is not its: the tree's entries, copied to its HOME
        assert seen["uid"] == box.sandbox.node_uid
        assert any(f.startswith("sipp_kernel.sipp_search-") and f.endswith(".nbi") for f in seen["copies"]), seen
