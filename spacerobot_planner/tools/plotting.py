"""
Figures of a plan, as in the paper's figures 3–5 and 7–10 (matplotlib, Agg).

One PNG with several panels: the C-space (2-DOF image; 3-DOF boundary voxels and
θ1 slices; more joints: the slice of the last two through the goal), the potential
φ = -log u on a log colour scale (3-DOF: the slice through the goal's θ1; more
joints: the same slice as the C-space's, with every joint along the path), the path
in C-space (grid nodes and spline, lines broken where a periodic joint wraps), and
the arm's motion in the plane with the target and the spacecraft body (stroboscopic
postures, start and goal highlighted).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap, LogNorm  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402

from ..cspace import build_cspace  # noqa: E402
from ..joint_space import wrap_angle_rad, wrap_rad  # noqa: E402

__all__ = ["plot_plan", "plot_reaction", "wrap_for_plot"]

_START, _GOAL, _PATH, _GRID = "#1f77b4", "#d62728", "#ff7f0e", "#2ca02c"


def wrap_for_plot(path_rad, lower_rad, periodic) -> np.ndarray:
    """Wrap periodic columns into [lower, lower + 2π) and put a NaN row at each seam crossing."""
    p = np.array(path_rad, dtype=float)
    if len(p) == 0:
        return p
    p = wrap_rad(p, periodic, lower_rad)
    jumps = np.zeros(len(p) - 1, dtype=bool)
    for a, per in enumerate(periodic):
        if per:
            jumps |= np.abs(np.diff(p[:, a])) > np.pi
    if not jumps.any():
        return p
    out = []
    for i in range(len(p)):
        out.append(p[i])
        if i < len(jumps) and jumps[i]:
            out.append(np.full(p.shape[1], np.nan))
    return np.array(out)


def _extent_deg(grid, ax0, ax1):
    v0, v1 = np.degrees(grid.axis_values_rad(ax0)), np.degrees(grid.axis_values_rad(ax1))
    h0, h1 = np.degrees(grid.step_rad[ax0]) / 2, np.degrees(grid.step_rad[ax1]) / 2
    return [v0[0] - h0, v0[-1] + h0, v1[0] - h1, v1[-1] + h1]


def _image(ax, data2d, grid, ax0, ax1, **kw):
    """Show data indexed [axis ax0, axis ax1] with ax0 horizontal."""
    return ax.imshow(np.asarray(data2d).T, origin="lower", extent=_extent_deg(grid, ax0, ax1),
                     aspect="auto", interpolation="nearest", **kw)


def _occ_cmap():
    return ListedColormap(["white", "#555555"])


def _plot_path_2d(ax, res, robot, a0, a1, label=True):
    per = robot.planned_periodic
    lo = robot.planned_lower_rad
    if len(res.grid_path_rad):
        g = np.degrees(wrap_for_plot(res.grid_path_rad, lo, per))
        ax.plot(g[:, a0], g[:, a1], ".", color=_GRID, ms=4, label="grid nodes" if label else None)
    if len(res.path_rad):
        p = np.degrees(wrap_for_plot(res.path_rad, lo, per))
        ax.plot(p[:, a0], p[:, a1], "-", color=_PATH, lw=2, label="spline path" if label else None)
    s = np.degrees(res.start_rad)
    ax.plot(s[a0], s[a1], "o", color=_START, ms=8, mec="k", label="start" if label else None)
    if res.goal_rad is not None:
        gq = np.degrees(res.goal_rad)
        ax.plot(gq[a0], gq[a1], "*", color=_GOAL, ms=14, mec="k", label="goal" if label else None)


def _potential_panel(ax, fig, phi, grid, a0, a1, title):
    phi = np.array(phi, dtype=float)
    finite = np.isfinite(phi)
    pos = phi[finite & (phi > 0)]
    if pos.size:
        vmin, vmax = max(pos.min(), 1e-12), max(pos.max(), pos.min() * 10)
        shown = np.where(finite, np.maximum(phi, vmin), np.nan)
        shown = np.ma.masked_invalid(shown)
        cmap = plt.get_cmap("viridis").with_extremes(bad="#555555")
        im = _image(ax, shown, grid, a0, a1, cmap=cmap, norm=LogNorm(vmin=vmin, vmax=vmax))
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02, label="φ = −log u (log scale)")
    ax.set_title(title, fontsize=10)


def _arm_panel(ax, res, scenario, n_poses=12):
    robot, scene = scenario.robot, scenario.scene
    if scene.target is not None:
        ax.add_patch(Polygon(scene.target.body_polygon_m, closed=True, fc="#bbbbbb", ec="k",
                             label="target body"))
        ax.add_patch(Polygon(scene.target.handle_polygon_m, closed=True, fc="#f2c80f", ec="k",
                             label="grasp handle"))
    for i, poly in enumerate(scene.debris_m):
        ax.add_patch(Polygon(poly, closed=True, fc="#999999", ec="k", hatch="//",
                             label="debris" if i == 0 else None))
    margin = scene.safety_margin_m
    path = res.path_rad if len(res.path_rad) else np.vstack([res.start_rad] + (
        [res.goal_rad] if res.goal_rad is not None else []))
    idx = np.unique(np.linspace(0, len(path) - 1, min(n_poses, len(path))).round().astype(int))
    cmap = plt.get_cmap("plasma")
    # free floating: the motion as it happens, inertial frame (attitude drifted, body moved)
    ff = getattr(res, "free_floating", None)
    drifted = ff is not None and len(ff.q_full_rad) == len(path)
    fulls = ff.q_full_rad if drifted else robot.full(path)
    shifts = ff.body_position_m if drifted else np.zeros((len(path), 2))
    for k, i in enumerate(idx):
        q_full = fulls[i]
        pts = robot.forward_kinematics(q_full) + shifts[i]
        first, last = i == idx[0], i == idx[-1] and len(res.path_rad) > 0
        color = _START if first else (_GOAL if last else cmap(0.15 + 0.7 * k / max(1, len(idx) - 1)))
        alpha = 1.0 if (first or last) else 0.45
        lw = 2.6 if (first or last) else 1.3
        body = robot.body_polygon_world(q_full[0]) + shifts[i]
        ax.add_patch(Polygon(body, closed=True, fill=False, ec=color, alpha=0.5 if (first or last) else 0.15,
                             lw=1.2))
        ax.plot(pts[:2, 0], pts[:2, 1], ":", color=color, alpha=alpha, lw=1)
        lab = "start" if first else ("goal" if last else None)
        ax.plot(pts[1:, 0], pts[1:, 1], "-o", color=color, alpha=alpha, lw=lw, ms=2.5, label=lab)
    if len(res.path_rad):
        tip = robot.tip_position(fulls) + shifts
        ax.plot(tip[:, 0], tip[:, 1], "--", color="k", lw=0.8, alpha=0.6, label="tip trace")
    ax.plot(0, 0, "k+", ms=8)
    reach = float(np.sum(robot.link_lengths_m))
    ax.set_xlim(-reach - 0.3, reach + 0.3)
    ax.set_ylim(-reach - 0.3, reach + 0.3)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    what = ("free floating, inertial frame: the body drifts" if drifted else "body turns with θ1")
    ax.set_title(f"arm motion ({what}; margin {margin} m)", fontsize=10)
    ax.legend(loc="lower right", fontsize=7)


def _title(res, scenario):
    if res.ok:
        return (f"{res.solver}: path {res.path_length_rad:.2f} rad, min clearance "
                f"{res.min_clearance_m:.3f} m, total {1e3 * res.timings_s['total']:.0f} ms "
                f"(grid {scenario.grid.label()})")
    return f"no path ({res.code}): {res.reason}"


def plot_plan(res, scenario, path, dpi: int = 110) -> None:
    """Write a PNG of a PlanResult (works without a path: shows what exists)."""
    robot = scenario.robot
    cs = res.cspace
    if cs is None:
        cs = build_cspace(robot, scenario.scene, scenario.grid)
    grid = cs.grid
    phi = res.field.potential() if res.field is not None else None
    names = robot.planned_names
    if robot.dof == 2:
        fig, axes = plt.subplots(1, 3, figsize=(18, 5.6))
        ax = axes[0]
        _image(ax, cs.occupied, grid, 0, 1, cmap=_occ_cmap(), vmin=0, vmax=1)
        _plot_path_2d(ax, res, robot, 0, 1)
        ax.set_title(f"C-space {grid.label()} (grey: collision incl. margin"
                     f"{', body at its start pose' if res.free_floating is not None else ''})", fontsize=10)
        ax.legend(loc="upper left", fontsize=7)
        ax = axes[1]
        if phi is not None:
            _potential_panel(ax, fig, phi, grid, 0, 1, "harmonic potential φ")
        else:
            _image(ax, cs.occupied, grid, 0, 1, cmap=_occ_cmap(), vmin=0, vmax=1)
            ax.set_title("no field (free-floating capture: its guide is planned in the drifted body's scene)"
                         if res.smoothing == "free_floating_capture" else "no field (planning stopped before it)",
                         fontsize=10)
        _plot_path_2d(ax, res, robot, 0, 1, label=False)
        for ax in axes[:2]:
            ax.set_xlabel(f"θ ({names[0]}) [deg]")
            ax.set_ylabel(f"θ ({names[1]}) [deg]")
        _arm_panel(axes[2], res, scenario)
    elif robot.dof > 3:
        fig = _plot_many_joints(res, scenario, cs, phi)
    else:
        fig = plt.figure(figsize=(19, 10.5))
        gs = fig.add_gridspec(2, 4)
        # 3-D boundary voxels of the obstacle region, subsampled
        ax3 = fig.add_subplot(gs[0, 0], projection="3d")
        occ = cs.occupied
        boundary = occ.copy()
        inner = occ.copy()
        for a in range(3):
            for s in (-1, 1):
                inner &= np.roll(occ, s, axis=a)
        boundary &= ~inner
        nodes = np.argwhere(boundary)
        if len(nodes) > 6000:
            nodes = nodes[np.random.default_rng(0).choice(len(nodes), 6000, replace=False)]
        pts = np.degrees(grid.config_of(nodes))
        ax3.scatter(pts[:, 0], pts[:, 1], pts[:, 2], s=2, c=pts[:, 0], cmap="Greys", alpha=0.25,
                    depthshade=False, label="obstacle surface (incl. margin)")
        lo, per = robot.planned_lower_rad, robot.planned_periodic
        if len(res.grid_path_rad):
            g = np.degrees(wrap_for_plot(res.grid_path_rad, lo, per))
            ax3.plot(g[:, 0], g[:, 1], g[:, 2], ".", color=_GRID, ms=4, label="grid path (descent)")
        if len(res.path_rad):
            p = np.degrees(wrap_for_plot(res.path_rad, lo, per))
            ax3.plot(p[:, 0], p[:, 1], p[:, 2], "-", color=_PATH, lw=2.5, label="smoothed path")
        s = np.degrees(res.start_rad)
        ax3.scatter(*s, color=_START, s=60, edgecolor="k", depthshade=False, label="start")
        if res.goal_rad is not None:
            ax3.scatter(*np.degrees(res.goal_rad), color=_GOAL, s=140, marker="*", edgecolor="k",
                        depthshade=False, label="goal")
        ax3.legend(loc="upper left", fontsize=6, framealpha=0.6)
        ax3.set_xlabel(f"{names[0]} [deg]")
        ax3.set_ylabel(f"{names[1]} [deg]")
        ax3.set_zlabel(f"{names[2]} [deg]", labelpad=2)
        ax3.set_title(f"C-space {grid.label()}: obstacle surface, path", fontsize=10)
        # potential: slice through the goal's θ1
        ax = fig.add_subplot(gs[0, 1])
        q_slice = res.goal_rad if res.goal_rad is not None else res.start_rad
        k_goal = grid.node_of(q_slice)[0]
        th = np.degrees(grid.axis_values_rad(0)[k_goal])
        if phi is not None:
            _potential_panel(ax, fig, phi[k_goal], grid, 1, 2, f"potential φ, slice {names[0]} = {th:.0f}°")
        else:
            _image(ax, occ[k_goal], grid, 1, 2, cmap=_occ_cmap(), vmin=0, vmax=1)
            ax.set_title(f"C-space slice {names[0]} = {th:.0f}° (no field)", fontsize=10)
        _plot_path_2d(ax, res, robot, 1, 2, label=False)
        ax.set_xlabel(f"{names[1]} [deg]")
        ax.set_ylabel(f"{names[2]} [deg]")
        # arm motion
        _arm_panel(fig.add_subplot(gs[0, 2:]), res, scenario)
        # θ1 slices of the C-space along the path
        if len(res.path_rad):
            pw = wrap_for_plot(res.path_rad, lo, per)
            pw = pw[np.isfinite(pw[:, 0])]
            picks = pw[np.linspace(0, len(pw) - 1, 4).round().astype(int), 0]
        else:
            picks = np.array([res.start_rad[0]] * 4)
        for c, th1 in enumerate(picks):
            ax = fig.add_subplot(gs[1, c])
            k = grid.node_of(np.array([th1, 0.0, 0.0]))[0]
            _image(ax, occ[k], grid, 1, 2, cmap=_occ_cmap(), vmin=0, vmax=1)
            thk = grid.axis_values_rad(0)[k]
            if len(res.path_rad):
                p = wrap_for_plot(res.path_rad, lo, per)
                near = np.abs(wrap_angle_rad(p[:, 0] - thk)) <= grid.step_rad[0] / 2
                pp = np.where(near[:, None], np.degrees(p), np.nan)
                ax.plot(np.degrees(p[:, 1]), np.degrees(p[:, 2]), "-", color=_PATH, lw=0.8, alpha=0.35)
                ax.plot(pp[:, 1], pp[:, 2], "-", color=_PATH, lw=3)
            ax.plot(s[1], s[2], "o", color=_START, ms=7, mec="k")
            if res.goal_rad is not None:
                gq = np.degrees(res.goal_rad)
                ax.plot(gq[1], gq[2], "*", color=_GOAL, ms=12, mec="k")
            ax.set_title(f"C-space slice {names[0]} = {np.degrees(thk):.0f}° (thick: path near it)",
                         fontsize=9)
            ax.set_xlabel(f"{names[1]} [deg]")
            ax.set_ylabel(f"{names[2]} [deg]")
    fig.suptitle(_title(res, scenario), fontsize=12)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def _plot_many_joints(res, scenario, cs, phi):
    """
    Return the figure of a plan over 4 or more planned joints.

    The C-space and the potential in the plane of the last two planned joints, sliced through
    the goal's nodes on the other axes (the start's without a goal); every joint along the
    path; the arm's motion.
    """
    robot, grid = scenario.robot, cs.grid
    names = robot.planned_names
    a0, a1 = robot.dof - 2, robot.dof - 1
    q_slice = res.goal_rad if res.goal_rad is not None else res.start_rad
    node = grid.node_of(q_slice)
    index = tuple(slice(None) if a in (a0, a1) else int(node[a]) for a in range(grid.ndim))
    at = ", ".join(f"{names[a]} = {np.degrees(grid.axis_values_rad(a)[node[a]]):.0f}°"
                   for a in range(grid.ndim) if a not in (a0, a1))
    fig = plt.figure(figsize=(19, 10.5))
    gs = fig.add_gridspec(2, 3)
    ax = fig.add_subplot(gs[0, 0])
    _image(ax, cs.occupied[index], grid, a0, a1, cmap=_occ_cmap(), vmin=0, vmax=1)
    _plot_path_2d(ax, res, robot, a0, a1)
    ax.set_title(f"C-space {grid.label()}, slice {at}\n(grey: collision incl. margin; path projected)",
                 fontsize=9)
    ax.legend(loc="upper left", fontsize=7)
    ax = fig.add_subplot(gs[0, 1])
    if phi is not None:
        _potential_panel(ax, fig, phi[index], grid, a0, a1, f"potential φ, slice {at}")
    else:
        _image(ax, cs.occupied[index], grid, a0, a1, cmap=_occ_cmap(), vmin=0, vmax=1)
        ax.set_title(f"C-space slice {at} (no field)", fontsize=9)
    _plot_path_2d(ax, res, robot, a0, a1, label=False)
    for ax in fig.axes[:2]:
        ax.set_xlabel(f"θ ({names[a0]}) [deg]")
        ax.set_ylabel(f"θ ({names[a1]}) [deg]")
    ax = fig.add_subplot(gs[1, 0:2])
    if len(res.path_rad):
        p = np.degrees(wrap_for_plot(res.path_rad, robot.planned_lower_rad, robot.planned_periodic))
        for a, name in enumerate(names):
            ax.plot(p[:, a], lw=1.8, label=name)
        ax.set_xlabel("path sample (≤ 0.5° apart)")
    else:
        ax.text(0.5, 0.5, "no path", ha="center", va="center", transform=ax.transAxes)
    ax.set_ylabel("joint angle [deg]")
    ax.set_title("joints along the path", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    _arm_panel(fig.add_subplot(gs[:, 2]), res, scenario)
    return fig


def plot_reaction(motion, path, dpi: int = 110) -> None:
    """
    Write a PNG of a ``timing.Motion``.

    Wheel momentum and torque against time with their limits (attitude held/commanded), and the
    free-floating attitude against time.
    """
    traj, r = motion.trajectory, motion.reaction
    t = traj.times_s
    fig, axes = plt.subplots(1, 3, figsize=(17, 4.6))
    for ax, series, limit, label in ((axes[0], r.wheel_momentum_Nms, r.max_wheel_momentum_Nms,
                                      "wheel momentum [N·m·s]"),
                                     (axes[1], r.wheel_torque_Nm, r.max_wheel_torque_Nm, "wheel torque [N·m]")):
        ax.plot(t, series, color=_PATH, lw=1.8)
        if limit is not None:
            for sign in (1, -1):
                ax.axhline(sign * limit, color=_GOAL, ls="--", lw=1.2, label="limit" if sign > 0 else None)
            ax.legend(loc="upper right", fontsize=8)
        ax.set_xlabel("t [s]")
        ax.set_ylabel(label)
        ax.set_title(f"{label.split(' [')[0]} (attitude {'held' if r.acs_mode == 'held' else 'if held'}), "
                     f"peak {np.max(np.abs(series)):.3g}", fontsize=10)
        ax.grid(alpha=0.3)
    ax = axes[2]
    att = np.degrees(r.free_floating_attitude_rad)
    ax.plot(t, att, color=_START, lw=1.8, label="free floating")
    ax.plot(t, np.degrees(r.planned_attitude_rad), color=_GRID, lw=1.2, ls="--", label="planned")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("attitude [deg]")
    ax.set_title(f"free-floating attitude: change {r.free_floating_attitude_change_deg:.2f}°, tip miss "
                 f"{r.free_floating_tip_miss_m:.3f} m", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.suptitle(f"spacecraft reaction ({r.acs_mode}): trajectory {traj.duration_s:.1f} s"
                 + ("" if r.ok else f" — refused: {r.reason}"), fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
