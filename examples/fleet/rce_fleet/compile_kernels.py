"""Compile every numba kernel of the fleet (its nodes' and the simulator's) into the tree's
cache: ``python -m rce_fleet.compile_kernels`` (``make bytecode``, as the tree's owner).
Sandboxed fleet nodes load them from there instead of compiling them in every container
(:mod:`rce_fleet.numba_cache`), and the simulator starts without compiling."""
from __future__ import annotations

from .lifelong import epibt, flow, kernels, spacetime, window
from .planning import sipp_kernel
from .sim import clearance, raycast


def main() -> None:
    """Compile (or load, when the tree's cache is current) each module's kernels."""
    for module in (sipp_kernel, kernels, flow, spacetime, window, epibt, raycast, clearance):
        module.warm_up()


if __name__ == "__main__":
    main()
