"""The local planner's arc geometry, compiled (numba, ``cache=True``): for each sampled arc,
its smallest distance to the lidar's hits, and to the point it steers for; for each direction
of a detour, the free length of its corridor; the hits in the robot's frame.

Why (py-spy of the live 100-robot fleet, ``bench/fleet_live.py --robots 100``): a k-d tree
of the hits (scipy's ``cKDTree``), built and queried with the arcs' 2,520 points at every
control step of every driving robot, took 16 % of the simulator process. The robots see tens
of hits within a metre, so a plain scan over them, pruned to the hits that can be within
``bound`` of an arc, costs a fraction of that, with the same distances.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..numba_cache import seed

seed(__file__)          # numba's cache entries prepared in the tree (sandboxed nodes)

__all__ = ["arc_clearance", "closest_approach", "corridor_free", "robot_frame", "warm_up"]


@njit(cache=True)
def _closest(ax, ay, tx, ty):
    n, k = ax.shape
    out = np.empty(n)
    for i in range(n):
        sq = np.inf
        for j in range(k):
            dx, dy = tx - ax[i, j], ty - ay[i, j]
            sq = min(sq, dx * dx + dy * dy)
        best = np.inf                      # hypot of the points that can be nearest, as numpy's hypot
        for j in range(k):
            dx, dy = tx - ax[i, j], ty - ay[i, j]
            if dx * dx + dy * dy <= sq * (1.0 + 1e-9):
                best = min(best, math.hypot(dx, dy))
        out[i] = best
    return out


@njit(cache=True)
def _clearance(ax, ay, pts, bound):
    n, k = ax.shape
    reach = 0.0
    for i in range(n):
        for j in range(k):
            reach = max(reach, math.hypot(ax[i, j], ay[i, j]))
    near = np.empty(pts.shape[0], dtype=np.int64)
    m = 0
    for q in range(pts.shape[0]):
        if math.hypot(pts[q, 0], pts[q, 1]) < reach + bound:
            near[m] = q
            m += 1
    out = np.full(n, np.inf)
    bb = bound * bound
    for i in range(n):
        x0, x1, y0, y1 = ax[i, 0], ax[i, 0], ay[i, 0], ay[i, 0]       # the arc's box, widened by bound
        for j in range(k):
            x0, x1 = min(x0, ax[i, j]), max(x1, ax[i, j])
            y0, y1 = min(y0, ay[i, j]), max(y1, ay[i, j])
        x0, x1, y0, y1 = x0 - bound, x1 + bound, y0 - bound, y1 + bound
        best = bb
        for q in range(m):
            px, py = pts[near[q], 0], pts[near[q], 1]
            if px < x0 or px > x1 or py < y0 or py > y1:
                continue
            for j in range(k):
                dx, dy = px - ax[i, j], py - ay[i, j]
                d = dx * dx + dy * dy
                if d < best:
                    best = d
        if best < bb:
            out[i] = math.sqrt(best)
    return out


def arc_clearance(ax: np.ndarray, ay: np.ndarray, points: np.ndarray, bound: float) -> np.ndarray:
    """(N,) float64: for each arc i, the smallest distance, m, from its points (``ax[i]``,
    ``ay[i]``; (N, K) float64, m) to ``points`` ((P, 2) float64, m); inf when it is ``bound`` m
    or more (as ``cKDTree.query(..., distance_upper_bound=bound)`` reports a distance)."""
    return _clearance(np.ascontiguousarray(ax, dtype=np.float64), np.ascontiguousarray(ay, dtype=np.float64),
                      np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2), float(bound))


@njit(cache=True)
def _corridors(ux, uy, pts, half):
    out = np.empty(ux.shape[0])
    hh = half * half
    for i in range(ux.shape[0]):
        best = np.inf
        for q in range(pts.shape[0]):
            a = ux[i] * pts[q, 0] + uy[i] * pts[q, 1]
            b = abs(ux[i] * pts[q, 1] - uy[i] * pts[q, 0])
            if b < half and a > 0.0:
                best = min(best, a - math.sqrt(max(hh - b * b, 0.0)))
        out[i] = max(best, 0.0)
    return out


def corridor_free(ux: np.ndarray, uy: np.ndarray, points: np.ndarray, half: float) -> np.ndarray:
    """(A,) float64: the free length, m, of a straight corridor of half-width ``half`` m from the
    origin along each unit direction (``ux``, ``uy``; (A,) float64) among ``points`` ((P, 2)
    float64, m): up to where its first point's disc would enter it (inf when none does)."""
    return _corridors(np.ascontiguousarray(ux, dtype=np.float64), np.ascontiguousarray(uy, dtype=np.float64),
                      np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2), float(half))


@njit(cache=True)
def _to_frame(pts, x, y, c, s, reach):
    out = np.empty((pts.shape[0], 2))
    m = 0
    nearest = np.inf
    for q in range(pts.shape[0]):
        dx, dy = pts[q, 0] - x, pts[q, 1] - y
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        r = math.hypot(lx, ly)
        if r < reach:
            out[m, 0], out[m, 1] = lx, ly
            m += 1
            nearest = min(nearest, r)
    return out[:m], nearest


def robot_frame(points: np.ndarray, x: float, y: float, yaw: float, reach: float) -> tuple[np.ndarray, float]:
    """The world ``points`` ((P, 2) float64, m) seen from the pose (x m, y m, yaw rad), those
    nearer than ``reach`` m: ((M, 2) float64, m; the distance, m, of the nearest, inf if none)."""
    return _to_frame(np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2), float(x), float(y),
                     math.cos(yaw), math.sin(yaw), float(reach))


def closest_approach(ax: np.ndarray, ay: np.ndarray, tx: float, ty: float) -> np.ndarray:
    """(N,) float64: for each arc i (points ``ax[i]``, ``ay[i]``; (N, K) float64, m), its
    points' smallest distance, m, to the point (``tx``, ``ty``) m."""
    return _closest(np.ascontiguousarray(ax, dtype=np.float64), np.ascontiguousarray(ay, dtype=np.float64),
                    float(tx), float(ty))


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels."""
    arc_clearance(np.zeros((1, 2)), np.zeros((1, 2)), np.ones((1, 2)), 1.0)
    closest_approach(np.zeros((1, 2)), np.zeros((1, 2)), 1.0, 1.0)
    corridor_free(np.ones(1), np.zeros(1), np.ones((1, 2)), 0.5)
    robot_frame(np.ones((1, 2)), 0.0, 0.0, 0.0, 2.0)
