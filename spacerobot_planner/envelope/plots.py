"""
The maps of a sweep, read like disturbance maps: feasibility and each metric over x–y.

One PNG per (start posture, target yaw): a panel of result codes (the feasibility map), then
one heatmap per metric that has a value somewhere (path length, clearance, duration, approach
error, wheel momentum and torque peaks, free-floating attitude change, plan time).  A cell is
the target body's centre; cells without a value (no path) are left grey.  Every panel draws
the spacecraft body at the start's attitude, the scenario's own target (dotted), and the arm's
reach: the target centres whose handle the arm can grasp perpendicularly at that yaw, joint
limits and collisions aside (dashed circles, see :func:`_reach`; a 2-DOF arm with the attitude
locked reaches them only along one circle, widened by ``grasp.max_approach_error_deg``).

Loads matplotlib (Agg); no rclpy.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..problem import Scenario
from ..results import CODES
from .sweep import PoseGrid

__all__ = ["plot_envelope", "METRICS", "figure_name"]

#: (column, label) of the metric panels, in order
METRICS = (
    ("path_length_rad", "path length (rad)"),
    ("min_clearance_m", "min clearance (m)"),
    ("duration_s", "trajectory duration (s)"),
    ("approach_error_deg", "approach error (deg)"),
    ("peak_wheel_momentum_Nms", "wheel momentum peak (N·m·s)"),
    ("peak_wheel_torque_Nm", "wheel torque peak (N·m)"),
    ("free_floating_attitude_change_deg", "free-floating attitude change (deg)"),
    ("plan_s", "plan time (s)"),
)
#: one colour per result code (the order of ``results.CODES``)
CODE_COLOURS = ("#2ca02c", "#7f7f7f", "#d62728", "#ff7f0e", "#c7c7c7", "#9467bd", "#8c564b", "#bcbd22",
                "#000000", "#e377c2")


def figure_name(start_index: int, yaw_deg: float, n_starts: int) -> str:
    """Return the PNG's file name of one (start, yaw): the yaw to 1e-6° (distinct yaws of a grid, distinct names)."""
    start = f"_start{start_index}" if n_starts > 1 else ""
    yaw = f"{yaw_deg:.6f}".rstrip("0").rstrip(".")
    return f"envelope{start}_yaw{'0' if yaw == '-0' else yaw}deg.png"


def _edges(centres) -> np.ndarray:
    c = np.asarray(centres, dtype=float)
    if len(c) == 1:
        return np.array([c[0] - 0.05, c[0] + 0.05])
    mid = 0.5 * (c[1:] + c[:-1])
    return np.concatenate([[2 * c[0] - mid[0]], mid, [2 * c[-1] - mid[-1]]])


def _reach(scenario: Scenario, start_rad, yaw_deg: float) -> tuple:
    """
    Return (centre (2,), inner, outer) of the target centres a perpendicular grasp can reach, m.

    At capture the last link points into the handle (absolute angle yaw + 270°), so its root
    (the wrist) lies ``L_last`` behind the grasp point and the target's centre ``L_last + d``
    beyond the wrist along that direction (d: half the body plus the handle).  The wrist ranges
    over the annulus of the links before the last about their base: the body's centre when the
    attitude is planned, else the shoulder at the start's attitude.  Joint limits and
    collisions are ignored (the sweep finds those).
    """
    robot, tgt = scenario.robot, scenario.scene.target
    links = np.asarray(robot.link_lengths_m, dtype=float)
    if 0 in robot.planned_joints:               # the attitude turns: the chain starts at the body's centre
        base, chain = np.zeros(2), links[:-1]
    else:
        base = robot.forward_kinematics(robot.full(np.asarray(start_rad)))[1]
        chain = links[1:-1]
    outer = float(chain.sum())
    inner = float(max(0.0, 2 * chain.max() - chain.sum())) if len(chain) else 0.0
    yaw = math.radians(yaw_deg)
    shift = (links[-1] + 0.5 * tgt.body_side_m + tgt.handle_side_m) * np.array([math.sin(yaw), -math.cos(yaw)])
    return base + shift, inner, outer


def _overlay(ax, scenario: Scenario, start_rad, yaw_deg: float) -> None:
    from matplotlib.patches import Circle, Polygon
    robot = scenario.robot
    attitude = float(robot.full(np.asarray(start_rad))[0])
    ax.add_patch(Polygon(robot.body_polygon_world(attitude), closed=True, fc="#dddddd", ec="k", lw=1.0,
                         zorder=3, label="spacecraft body"))
    tgt = scenario.scene.target
    ax.add_patch(Polygon(tgt.body_polygon_m, closed=True, fill=False, ec="k", ls=":", lw=1.0, zorder=3,
                         label="scenario's target"))
    centre, inner, outer = _reach(scenario, start_rad, yaw_deg)
    ax.add_patch(Circle(centre, outer, fill=False, ec="#1f3b73", ls="--", lw=1.0, zorder=3,
                        label="reach: perpendicular grasp"))
    if 0 < inner < outer:
        ax.add_patch(Circle(centre, inner, fill=False, ec="#1f3b73", ls="--", lw=1.0, zorder=3))


def _panel_limits(ax, xe, ye, body, target) -> None:
    """
    Show the swept cells, the spacecraft body and the scenario's target (outlines k×2, m), 0.2 m around.

    The cells' edges in either order (a range given from its larger end: ``--x-m -2.6 -3.6 3``).
    """
    x = np.concatenate([np.asarray(xe, dtype=float), body[:, 0], target[:, 0]])
    y = np.concatenate([np.asarray(ye, dtype=float), body[:, 1], target[:, 1]])
    ax.set_xlim(x.min() - 0.2, x.max() + 0.2)
    ax.set_ylim(y.min() - 0.2, y.max() + 0.2)
    ax.set_aspect("equal")
    ax.set_xlabel("target x (m)")
    ax.set_ylabel("target y (m)")


def plot_envelope(rows, scenario: Scenario, grid: PoseGrid, out_dir, dpi: int = 100) -> list:
    """
    Write one PNG per (start, yaw) into ``out_dir``; return their paths.

    ``rows``: the sweep's rows (``sweep.COLUMNS``), one per pose of ``grid``.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap
    from matplotlib.patches import Patch

    na, ny, nx, ns = grid.shape
    by_id = {r["pose_id"]: r for r in rows}
    xe, ye = _edges(grid.x_m), _edges(grid.y_m)
    code_cmap = ListedColormap(CODE_COLOURS[:len(CODES)])
    code_norm = BoundaryNorm(np.arange(len(CODES) + 1) - 0.5, len(CODES))
    paths = []
    for s in range(ns):
        for a in range(na):
            ids = ((a * ny + np.arange(ny)[:, None]) * nx + np.arange(nx)[None, :]) * ns + s
            table = [[by_id.get(int(i)) for i in line] for line in ids]

            def values(col):
                return np.array([[np.nan if r is None else float(r[col]) for r in line] for line in table])

            body = scenario.robot.body_polygon_world(float(scenario.robot.full(np.asarray(grid.starts_rad[s]))[0]))
            codes = np.array([[np.nan if r is None else CODES.index(r["code"]) for r in line] for line in table])
            panels = [(c, lab, values(c)) for c, lab in METRICS]
            panels = [p for p in panels if np.isfinite(p[2]).any()]
            n = 1 + len(panels)
            cols = min(3, n)
            nrows = math.ceil(n / cols)
            fig, axes = plt.subplots(nrows, cols, figsize=(5.2 * cols, 4.6 * nrows), squeeze=False)
            flat = axes.ravel()
            ax = flat[0]
            ax.pcolormesh(xe, ye, np.ma.masked_invalid(codes), cmap=code_cmap, norm=code_norm)
            present = sorted({int(c) for c in codes[np.isfinite(codes)]})
            ok = int(np.sum(codes == CODES.index("ok")))
            _overlay(ax, scenario, grid.starts_rad[s], grid.yaw_deg[a])
            handles = [Patch(color=CODE_COLOURS[k], label=CODES[k]) for k in present]
            ax.legend(handles=handles + ax.get_legend_handles_labels()[0], fontsize=7, loc="upper center",
                      bbox_to_anchor=(0.5, -0.12), ncol=3)      # below the map: "best" could cover cells
            ax.set_title(f"feasibility: {ok} of {nx * ny} poses ok", fontsize=10)
            _panel_limits(ax, xe, ye, body, scenario.scene.target.body_polygon_m)
            for ax, (col, label, vals) in zip(flat[1:], panels):
                lo, hi = np.nanmin(vals), np.nanmax(vals)
                flat_map = hi - lo <= 1e-9 * max(1.0, abs(hi))     # e.g. an approach error of 0 everywhere
                im = ax.pcolormesh(xe, ye, np.ma.masked_invalid(vals), cmap="viridis",
                                   vmin=hi - 1.0 if flat_map else None, vmax=hi + 1.0 if flat_map else None)
                ax.set_facecolor("#eeeeee")
                fig.colorbar(im, ax=ax, shrink=0.85)
                _overlay(ax, scenario, grid.starts_rad[s], grid.yaw_deg[a])
                ax.set_title(f"{label}: {round(float(hi), 6):g} everywhere" if flat_map else label, fontsize=10)
                _panel_limits(ax, xe, ye, body, scenario.scene.target.body_polygon_m)
            for ax in flat[n:]:
                ax.set_visible(False)
            start_deg = " ".join(f"{v:.1f}" for v in np.degrees(grid.starts_rad[s]))
            fig.suptitle(f"capture envelope: target yaw {grid.yaw_deg[a]:.1f}°, start [{start_deg}]° "
                         f"({', '.join(scenario.robot.planned_names)})", fontsize=12)
            fig.tight_layout()
            path = Path(out_dir) / figure_name(s, grid.yaw_deg[a], ns)
            fig.savefig(path, dpi=dpi)
            plt.close(fig)
            paths.append(path)
    return paths
