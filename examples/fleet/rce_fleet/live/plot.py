"""PNGs of a fleet run: a mission's map, grid, blocked cells and each robot's driven path
(:func:`plot_run`); a run by tasks' tasks done over time and the robots' activity (:func:`plot_tasks`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..maps.geometry import GridGeometry

__all__ = ["plot_run", "plot_tasks"]


def plot_run(path: str | Path, occ_map, geo: GridGeometry, traces: dict[str, list[tuple[float, float]]],
             starts: dict[str, int], goals: dict[str, int], blocked: dict[int, str], title: str = "",
             reached: dict[str, bool] | None = None) -> Path:
    """Write the PNG to ``path`` (parent created); returns it.

    traces: robot -> [(x, y), ...] ground-truth positions; starts/goals: robot -> cell;
    blocked: cell -> source (operator blocks hatched red, lidar blocks orange)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    occ = np.asarray(occ_map.occupancy)
    img = np.full(occ.shape, 0.55)
    img[(occ >= 0) & (occ < 50)] = 1.0
    img[occ >= 50] = 0.0
    ox, oy, _ = occ_map.origin
    res = occ_map.resolution
    h, w = occ.shape
    gx0, gy0 = geo.grid_corner()
    gx1, gy1 = gx0 + geo.cols * geo.cell_w_m, gy0 - geo.rows * geo.cell_h_m
    span = max(gx1 - gx0, gy0 - gy1)
    fig_w = 8.0
    fig_h = max(4.0, min(14.0, fig_w * (gy0 - gy1) / max(gx1 - gx0, 1e-6)))
    fig, ax = plt.subplots(figsize=(fig_w, fig_h), dpi=110)
    ax.imshow(img, cmap="gray", vmin=0, vmax=1, extent=(ox, ox + w * res, oy, oy + h * res), origin="upper",
              interpolation="nearest")
    # grid: free cells lightly tinted, non-free cells shaded
    small = geo.n_cells <= 256
    for cell in range(geo.n_cells):
        r, c = geo.rc(cell)
        x0, y0 = gx0 + c * geo.cell_w_m, gy0 - r * geo.cell_h_m
        corners = [(x0, y0), (x0 + geo.cell_w_m, y0), (x0 + geo.cell_w_m, y0 - geo.cell_h_m), (x0, y0 - geo.cell_h_m)]
        if cell in blocked:
            lidar = str(blocked[cell]).startswith("lidar")
            ax.add_patch(Polygon(corners, closed=True, facecolor=("orange" if lidar else "red"), alpha=0.45,
                                 hatch="xx", edgecolor="darkred", lw=0.8))
        elif not geo.free[cell]:
            ax.add_patch(Polygon(corners, closed=True, facecolor="black", alpha=0.12, lw=0))
        if small:
            cx, cy = geo.center(cell)
            ax.text(cx, cy, str(cell), ha="center", va="center", fontsize=6, color="0.45")
    lw = 0.4 if not small else 0.6
    for c in range(geo.cols + 1):
        x = gx0 + c * geo.cell_w_m
        ax.plot([x, x], [gy0, gy1], color="tab:blue", lw=lw, alpha=0.5)
    for r in range(geo.rows + 1):
        y = gy0 - r * geo.cell_h_m
        ax.plot([gx0, gx1], [y, y], color="tab:blue", lw=lw, alpha=0.5)
    cmap = plt.get_cmap("tab10" if len(traces) <= 10 else "tab20")
    ms = 7 if span < 15 else 5
    for i, rid in enumerate(sorted(traces, key=lambda robot_id: (len(robot_id), robot_id))):
        col = cmap(i % cmap.N)
        pts = np.asarray(traces[rid], dtype=float).reshape(-1, 2)
        ok = "" if reached is None else (" (reached)" if reached.get(rid) else " (NOT reached)")
        if len(pts):
            ax.plot(pts[:, 0], pts[:, 1], "-", color=col, lw=1.8, label=f"{rid}{ok}")
        if rid in starts:
            sx, sy = geo.center(starts[rid])
            ax.plot(sx, sy, "o", color=col, ms=ms, mec="black", mew=0.6)
        if rid in goals and goals[rid] is not None and geo.valid(goals[rid]):
            ex, ey = geo.center(goals[rid])
            ax.plot(ex, ey, "*", color=col, ms=ms + 5, mec="black", mew=0.6)
    pad = 0.3
    ax.set_xlim(gx0 - pad, gx1 + pad)
    ax.set_ylim(gy1 - pad, gy0 + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title or "fleet run: driven paths (o start, * goal; red: blocked cells)", fontsize=9)
    if traces:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_tasks(path: str | Path, timeline: list[tuple[float, int, dict[str, str]]], activities: tuple[str, ...],
               title: str = "") -> Path:
    """Write the PNG of a run by tasks to ``path`` (parent created); returns it. Top: tasks done
    over sim time; bottom: how many robots are in each of ``activities`` (stacked).

    timeline: [(sim s, tasks done, {robot: activity})], one sample per sim second. Raises
    ValueError for an empty timeline."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not timeline:
        raise ValueError("no sample of the run to plot")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    t = np.array([x[0] for x in timeline])
    done = np.array([x[1] for x in timeline])
    counts = np.array([[sum(1 for a in x[2].values() if a == act) for x in timeline] for act in activities])
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True, height_ratios=(1, 1.2))
    ax1.plot(t, done, color="C2")
    ax1.set_ylabel("tasks done")
    ax1.set_title(title, fontsize=10)
    ax1.grid(alpha=0.3)
    colours = ("tab:cyan", "tab:green", "gold", "tab:purple", "tab:blue", "lightgrey")
    ax2.stackplot(t, counts, labels=activities, colors=colours[:len(activities)])
    ax2.set_ylabel("robots")
    ax2.set_xlabel("simulated s")
    ax2.legend(loc="upper left", fontsize=7, ncol=len(activities))
    ax2.set_ylim(0, max(1, counts.sum(axis=0).max()) * 1.25)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
