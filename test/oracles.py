"""
The tests' oracles, each written once, sharing no code with what they check.

Grids (the field and descent tests; flood fills of the property tests)
    ``face_neighbours``: every node's 2n face neighbours from the grid's definition alone
    (periodic axes wrap, bounded axes end in a wall, cut edges removed); on it a sparse
    adjacency, connectivity and shortest grid paths (``scipy.sparse.csgraph``), the
    brute-force neighbour checks (largest neighbour, steepest strictly higher neighbour,
    where steepest ascent ends) and the harmonic field by a direct sparse solve of its
    Dirichlet problem (``harmonic_log_u``).
Geometry
    Segment–polygon distance in plain Python floats (Cramer's rule, winding numbers,
    projections) and with shapely (GEOS); the arm's joint points from complex numbers.
Paths and trajectories
    Dense linear samples, the wrapped difference of angles, TOPP-RA's time-optimal
    duration, velocity and acceleration limits by finite differences of the positions.
The controller's motion
    joint_trajectory_controller's interpolation of published points rebuilt with SciPy
    (``BPoly.from_derivatives`` quintics, ``CubicHermiteSpline``, ``np.interp``).
Dynamics
    Momentum sums about the system's centre of mass from the joint points by finite
    differences, the wheel's momentum and torque, a free-floating simulator.
"""

import cmath
import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
from scipy.interpolate import BPoly, CubicHermiteSpline, PPoly


# ===================================================================== grids
def face_neighbours(shape, periodic, cut_edges=None) -> np.ndarray:
    """
    Return the flat index of every node's face neighbours, int64 (2 ndim, *shape).

    Row 2a holds the neighbour one step down axis a, row 2a + 1 the one a step up (the
    fixed order (axis 0, -1), (axis 0, +1), (axis 1, -1), ...).  A periodic axis wraps (the
    last node's upper neighbour is node 0); beyond the end of a bounded axis, and across
    an edge of ``cut_edges`` (flat node pairs, int (k, 2)), the entry is -1.
    """
    shape = tuple(int(n) for n in shape)
    coords = np.indices(shape)
    out = np.empty((2 * len(shape),) + shape, np.int64)
    for a, n in enumerate(shape):
        for s, d in enumerate((-1, 1)):
            moved = coords.copy()
            moved[a] += d
            if periodic[a]:
                moved[a] %= n
                inside = np.ones(shape, bool)
            else:
                inside = (moved[a] >= 0) & (moved[a] < n)
                moved[a][~inside] = 0
            out[2 * a + s] = np.where(inside, np.ravel_multi_index(tuple(moved), shape), -1)
    if cut_edges is not None:
        flat = out.reshape(len(out), -1)
        for p, q in np.asarray(cut_edges, np.int64).reshape(-1, 2):
            if not (flat[:, p] == q).any():
                raise ValueError(f"cut edge ({p}, {q}) joins no face neighbours")
            flat[flat[:, p] == q, p] = -1
            flat[flat[:, q] == p, q] = -1
    return out


def neighbour_values(values: np.ndarray, nbr: np.ndarray, fill=-np.inf) -> np.ndarray:
    """Return the value at each face neighbour (``nbr`` from ``face_neighbours``), ``fill`` where there is none."""
    return np.where(nbr >= 0, values.ravel()[np.maximum(nbr, 0)], fill)


def adjacency(occupied: np.ndarray, nbr: np.ndarray) -> sp.csr_matrix:
    """
    Return the face edges between free nodes, sparse (N, N) over the flat grid.

    Entry (i, j) counts the face steps from i to j (2 where a periodic axis of 2 nodes
    joins them both ways).
    """
    free = ~np.asarray(occupied, bool).ravel()
    rows, cols = [], []
    for k in range(len(nbr)):
        j = nbr[k].ravel()
        ok = free & (j >= 0)
        ok[ok] = free[j[ok]]
        rows.append(np.flatnonzero(ok))
        cols.append(j[ok])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    return sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(free.size, free.size))


def connected(occupied: np.ndarray, periodic, sources, cut_edges=None) -> np.ndarray:
    """
    Return the free nodes joined to a free node of ``sources`` by face steps, bool (grid shape).

    ``sources``: int (k, ndim) nodes (one node: a tuple); obstacle sources join nothing.
    """
    occ = np.asarray(occupied, bool)
    src = np.asarray(sources, np.int64).reshape(-1, occ.ndim)
    src = src[~occ[tuple(src.T)]]
    _, label = csgraph.connected_components(adjacency(occ, face_neighbours(occ.shape, periodic, cut_edges)),
                                            directed=False)
    flat = np.ravel_multi_index(tuple(src.T), occ.shape)
    return (np.isin(label, label[flat]) & ~occ.ravel()).reshape(occ.shape)


def shortest_grid_path(occupied: np.ndarray, periodic, start, goal) -> np.ndarray:
    """Return a shortest face-step walk of free nodes from ``start`` to ``goal``, int (m, ndim)."""
    occ = np.asarray(occupied, bool)
    s, g = (int(np.ravel_multi_index(tuple(n), occ.shape)) for n in (start, goal))
    _, pred = csgraph.breadth_first_order(adjacency(occ, face_neighbours(occ.shape, periodic)), s,
                                          directed=False, return_predecessors=True)
    walk = [g]
    while walk[-1] != s:
        if pred[walk[-1]] < 0:
            raise ValueError(f"no free walk from {tuple(start)} to {tuple(goal)}")
        walk.append(int(pred[walk[-1]]))
    return np.stack(np.unravel_index(np.array(walk[::-1]), occ.shape), axis=1)


def neighbour_max(log_u: np.ndarray, periodic, cut_edges=None) -> np.ndarray:
    """Return the largest face-neighbour value of every node (-inf beyond walls and cut edges)."""
    return neighbour_values(log_u, face_neighbours(log_u.shape, periodic, cut_edges)).max(axis=0)


def steepest_successors(log_u: np.ndarray, periodic) -> np.ndarray:
    """
    Return each node's next step under steepest ascent of ``log_u``, flat int64 (grid shape).

    The face neighbour with the largest value if that is strictly above the node's own; ties
    go to the first in the fixed order (axis 0, -1), (axis 0, +1), (axis 1, -1), ...  -1
    where no neighbour is higher, and at nodes where log u = -inf (no walk starts there).
    """
    nbr = face_neighbours(log_u.shape, periodic)
    vals = neighbour_values(log_u, nbr)
    best = log_u.copy()
    succ = np.full(log_u.shape, -1, np.int64)
    for k in range(len(nbr)):
        up = vals[k] > best
        best[up] = vals[k][up]
        succ[up] = nbr[k][up]
    succ[log_u == -np.inf] = -1
    return succ


def ascent_walk(succ: np.ndarray, goal_mask: np.ndarray, start) -> np.ndarray:
    """Return the nodes of the ascent from ``start`` (``succ`` from ``steepest_successors``), int (m, ndim)."""
    nxt, goal = succ.ravel(), goal_mask.ravel()
    f = int(np.ravel_multi_index(tuple(start), succ.shape))
    walk = [f]
    while not goal[f] and nxt[f] >= 0:
        f = int(nxt[f])
        walk.append(f)
    return np.stack(np.unravel_index(np.array(walk), succ.shape), axis=1)


def ascent_reaches_goal(succ: np.ndarray, goal_mask: np.ndarray) -> np.ndarray:
    """Return where the ascent (``succ``) ends on a goal node, bool (grid shape): pointer doubling."""
    goal = goal_mask.ravel()
    end = np.where(succ.ravel() >= 0, succ.ravel(), np.arange(succ.size))
    end[goal] = np.flatnonzero(goal)
    while True:
        nxt = end[end]
        if np.array_equal(nxt, end):
            return goal[end].reshape(succ.shape)
        end = nxt


#: A band keeps the values at or above this, relative to its largest boundary value.
FIELD_BAND_FLOOR = 1e-150


def harmonic_log_u(occupied: np.ndarray, periodic, goals, cut_edges=None) -> np.ndarray:
    """
    Return log u of the harmonic field, by direct sparse solves.

    The discrete Dirichlet problem the field documents (spacerobot_planner.field), set up
    here from the grid alone: u = 1 on the goal nodes; on every other free node joined to a
    goal by face steps, 2n u = the sum of u over its 2n face neighbours, where a wall (beyond
    a bounded axis), an obstacle and a cut edge count as u = 0; periodic axes wrap.  Returns
    float64 of the grid's shape: 0 on the goals, -inf at obstacles and at free nodes not
    joined to a goal.

    u falls below any double's range in mazes (1e-561), so the solve goes by bands of
    scale: all unknown nodes at once; the values below ``FIELD_BAND_FLOOR`` then make up a
    problem of their own whose boundary values are the kept ones divided by the largest of
    them, and so on.  The matrix 2n I - A is a symmetric M-matrix, so its LU factors with
    diagonal pivots add only terms of one sign: every value keeps its relative precision.
    """
    occ = np.asarray(occupied, bool)
    deg = 2 * occ.ndim
    goal_flat = np.unique(np.ravel_multi_index(tuple(np.asarray(goals, np.int64).reshape(-1, occ.ndim).T),
                                               occ.shape))
    if occ.ravel()[goal_flat].any():
        raise ValueError("a goal node is an obstacle")
    adj = adjacency(occ, face_neighbours(occ.shape, periodic, cut_edges))
    _, label = csgraph.connected_components(adj, directed=False)
    joined = np.isin(label, label[goal_flat]) & ~occ.ravel()
    log_u = np.full(occ.size, -np.inf)
    log_u[goal_flat] = 0.0
    known = np.zeros(occ.size, bool)
    known[goal_flat] = True
    # the unknowns with an even coordinate sum first: MMD then fills the factors least
    parity = np.indices(occ.shape).sum(axis=0).ravel() % 2
    todo = np.flatnonzero(joined & ~known)
    todo = todo[np.argsort(parity[todo], kind="stable")]
    while todo.size:
        rows = adj[todo]
        kn = np.flatnonzero(known)
        to_known = rows[:, kn]
        touched = np.unique(to_known.indices)
        scale = log_u[kn[touched]].max()
        boundary = np.zeros(kn.size)
        boundary[touched] = np.exp(log_u[kn[touched]] - scale)
        rhs = to_known @ boundary
        lap = (sp.identity(todo.size, format="csc") * deg - rows[:, todo]).tocsc()
        x = spla.splu(lap, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                      options={"SymmetricMode": True}).solve(rhs)
        keep = x >= FIELD_BAND_FLOOR
        if not keep.any():
            raise RuntimeError("harmonic_log_u: a band kept no value")
        log_u[todo[keep]] = np.log(x[keep]) + scale
        known[todo[keep]] = True
        todo = todo[~keep]
    return log_u.reshape(occ.shape)


# ================================================================== geometry
def arm_points(robot, q_full) -> np.ndarray:
    """
    Return the arm's joint points, (..., n_joints + 1, 2) metres, from complex numbers.

    The origin, then the end of each link: link k points at the sum of the first k joint
    angles (``robot.link_lengths_m``).
    """
    q_full = np.asarray(q_full, dtype=float)
    steps = np.asarray(robot.link_lengths_m, dtype=float) * np.exp(1j * np.cumsum(q_full, axis=-1))
    z = np.concatenate([np.zeros(q_full.shape[:-1] + (1,), complex), np.cumsum(steps, axis=-1)], axis=-1)
    return np.stack([z.real, z.imag], axis=-1)


def body_polygon(robot, attitude_rad: float) -> np.ndarray:
    """Return the spacecraft body's outline turned by the attitude, (k, 2) metres."""
    z = (robot.body_polygon_m[:, 0] + 1j * robot.body_polygon_m[:, 1]) * cmath.exp(1j * float(attitude_rad))
    return np.stack([z.real, z.imag], axis=1)


def _polygons(robot, scene, attitude_rad):
    return [body_polygon(robot, attitude_rad)] + [np.asarray(p, dtype=float) for p in scene.obstacle_polygons_m]


def ref_point_seg(p, a, b):
    """Return the distance from point p to segment ab (projection, clamped)."""
    ax, ay = a
    dx, dy = b[0] - ax, b[1] - ay
    L2 = dx * dx + dy * dy
    t = 0.0 if L2 == 0 else max(0.0, min(1.0, ((p[0] - ax) * dx + (p[1] - ay) * dy) / L2))
    return math.hypot(ax + t * dx - p[0], ay + t * dy - p[1])


def ref_seg_seg_intersect(a, b, c, d):
    """Return whether segments ab and cd cross (parametric, Cramer's rule; parallel: no)."""
    r = (b[0] - a[0], b[1] - a[1])
    s = (d[0] - c[0], d[1] - c[1])
    den = r[0] * s[1] - r[1] * s[0]
    qp = (c[0] - a[0], c[1] - a[1])
    if abs(den) < 1e-15:
        return False       # parallel: touching handled by the distance below
    t = (qp[0] * s[1] - qp[1] * s[0]) / den
    u = (qp[0] * r[1] - qp[1] * r[0]) / den
    return 0.0 <= t <= 1.0 and 0.0 <= u <= 1.0


def ref_winding_inside(p, poly):
    """Return whether p lies inside the polygon (winding number)."""
    angle = 0.0
    n = len(poly)
    for i in range(n):
        a = (poly[i][0] - p[0], poly[i][1] - p[1])
        b = (poly[(i + 1) % n][0] - p[0], poly[(i + 1) % n][1] - p[1])
        angle += math.atan2(a[0] * b[1] - a[1] * b[0], a[0] * b[0] + a[1] * b[1])
    return abs(angle) > math.pi


def ref_seg_poly_distance(a, b, poly):
    """Return the distance from segment ab to the polygon (0 inside or crossing)."""
    if ref_winding_inside(a, poly):
        return 0.0
    best = math.inf
    n = len(poly)
    for i in range(n):
        c, d = poly[i], poly[(i + 1) % n]
        if ref_seg_seg_intersect(a, b, c, d):
            return 0.0
        best = min(best, ref_point_seg(a, c, d), ref_point_seg(b, c, d),
                   ref_point_seg(c, a, b), ref_point_seg(d, a, b))
    return best


def ref_clearance(robot, scene, q, links=None):
    """
    Return the clearance of links from the body and the obstacles, plain Python floats.

    ``links``: link indices (default ``robot.checked_links``; a test of longer chains passes
    every arm link, ``range(1, n_joints)``, its own choice).
    """
    q_full = robot.full(q)
    pts = arm_points(robot, q_full).tolist()
    polys = [p.tolist() for p in _polygons(robot, scene, q_full[0])]
    return min(ref_seg_poly_distance(pts[k], pts[k + 1], poly)
               for k in (robot.checked_links if links is None else links) for poly in polys)


def shapely_clearance(robot, scene, q):
    """Return the clearance of the checked links from the body and the obstacles, by shapely (GEOS)."""
    from shapely.geometry import LineString, Polygon
    q_full = robot.full(q)
    pts = arm_points(robot, q_full)
    return min(LineString([pts[k], pts[k + 1]]).distance(Polygon(poly))
               for k in robot.checked_links for poly in _polygons(robot, scene, q_full[0]))


def shapely_depth(robot, scene, q):
    """Return the deepest point of the checked links inside an obstacle (shapely), metres."""
    from shapely.geometry import LineString, Polygon
    pts = arm_points(robot, robot.full(q))
    polys = [Polygon(p) for p in scene.obstacle_polygons_m]
    best = 0.0
    for k in robot.checked_links:
        line = LineString([pts[k], pts[k + 1]])
        for poly in polys:
            inside = line.intersection(poly)
            if inside.is_empty:
                continue
            for s in np.linspace(0.0, inside.length, 400):
                best = max(best, poly.exterior.distance(inside.interpolate(s)))
    return best


def shapely_penetration(robot, scene, q, spacing_m=2.5e-4):
    """
    Return how deep the checked links reach into the posed body or an obstacle (shapely), metres.

    Each link sampled every ``spacing_m`` at most; the samples GEOS finds inside a polygon,
    their largest distance to its boundary (0 when none is inside): within ``spacing_m / 2``.
    """
    import shapely
    from shapely.geometry import Polygon
    q_full = robot.full(q)
    pts = arm_points(robot, q_full)
    best = 0.0
    for poly in (Polygon(p) for p in _polygons(robot, scene, q_full[0])):
        for k in robot.checked_links:
            a, b = pts[k], pts[k + 1]
            n = int(np.ceil(np.linalg.norm(b - a) / spacing_m)) + 1
            xy = a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)
            inside = shapely.contains_xy(poly, xy[:, 0], xy[:, 1])
            if inside.any():
                best = max(best, float(shapely.distance(poly.exterior, shapely.points(xy[inside])).max()))
    return best


def inside_target_or_margin(robot, scene, q_full, body_pos, n=200):
    """
    Return per configuration whether links 2-3 come within the margin of the target's body.

    The arm at ``q_full`` (K, 3) with its base at ``body_pos`` (K, 2), inertial frame; n points
    per link against the target's axis-aligned square body.
    """
    points = arm_points(robot, q_full) + np.asarray(body_pos)[:, None, :]
    cx, cy = scene.target.center_m
    half = 0.5 * scene.target.body_side_m
    f = np.linspace(0, 1, n)[None, :, None]
    hit = np.zeros(len(points), bool)
    for k in (1, 2):
        p = points[:, k, None, :] + f * (points[:, k + 1, None, :] - points[:, k, None, :])
        dx = np.maximum(np.abs(p[..., 0] - cx) - half, 0.0)
        dy = np.maximum(np.abs(p[..., 1] - cy) - half, 0.0)
        hit |= np.any(np.hypot(dx, dy) <= scene.safety_margin_m, axis=1)
    return hit


def link3_and_normal_deg(robot, target, q_full):
    """
    Return the angle between link 3 and the handle's inward normal, degrees.

    Link 3 from the joint points; the normal from the target's yaw (the handle sits on the
    target's local +y face).
    """
    pts = arm_points(robot, q_full)
    link = (pts[3] - pts[2]) / np.linalg.norm(pts[3] - pts[2])
    inward = np.array([np.sin(target.yaw_rad), -np.cos(target.yaw_rad)])
    return float(np.degrees(np.arccos(np.clip(link @ inward, -1.0, 1.0))))


# ===================================================== paths and trajectories
def edge_clearance(sc, a, b, step_rad=math.radians(0.25)) -> float:
    """
    Return the least clearance (``ref_clearance``) at dense samples of the straight motion between grid nodes a and b.

    a, b: flat node indices of ``sc.grid``; samples at most ``step_rad`` apart (across a periodic
    seam: one step the short way).
    """
    grid = sc.grid
    qa = grid.config_of(np.array(np.unravel_index(a, grid.shape)))
    qb = grid.config_of(np.array(np.unravel_index(b, grid.shape)))
    d = qb - qa
    per = np.asarray(grid.periodic)
    d[per] = (d[per] + math.pi) % (2 * math.pi) - math.pi
    k = max(1, int(math.ceil(np.max(np.abs(d)) / step_rad)))
    return min(ref_clearance(sc.robot, sc.scene, qa + t * d) for t in np.linspace(0.0, 1.0, k + 1))


def wrap_diff(a, b=0.0):
    """Return a - b wrapped into [-π, π)."""
    return (np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi


def dense_samples(path_rad: np.ndarray, step_rad: float = np.radians(0.25)) -> np.ndarray:
    """Return the path's polyline sampled linearly, consecutive samples at most step_rad apart (Euclidean)."""
    out = [path_rad[:1]]
    for a, b in zip(path_rad[:-1], path_rad[1:]):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_rad)))
        out.append(a + (np.arange(1, n + 1)[:, None] / n) * (b - a))
    return np.concatenate(out)


def finite_differences(t, q, v0):
    """
    Return segment velocities and point accelerations of a sampled motion.

    Segment velocities Δq/Δt, and at each point the change of segment velocity over half the
    neighbouring durations (from ``v0`` before the first point; rest after the last).
    """
    dt = t[1:] - t[:-1]
    w = (q[1:] - q[:-1]) / dt[:, None]
    before = np.vstack([v0[None, :], w])
    after = np.vstack([w, np.zeros((1, q.shape[1]))])
    half = np.concatenate([[0.0], dt / 2]) + np.concatenate([dt / 2, [0.0]])
    return w, (after - before) / half[:, None]


LIMIT_TOL = 1e-9


def check_trajectory(traj, path, vmax, amax, v0=None, dense=True, consistency=None):
    """
    Assert that a trajectory follows ``path`` within the limits.

    Exact ends, increasing times, ``v0`` at the start and rest at the end, published
    velocities and accelerations and the finite differences of the positions within
    ``vmax`` / ``amax``; with ``consistency``, the published values match the differences
    (that fraction of the limits); with ``dense``, no step above 0.5°.
    """
    t, q = traj.times_s, traj.positions_rad
    v0 = np.zeros(q.shape[1]) if v0 is None else np.asarray(v0)
    assert t[0] == 0.0 and np.all(np.diff(t) > 0.0)
    np.testing.assert_array_equal(q[0], np.asarray(path)[0])
    np.testing.assert_array_equal(q[-1], np.asarray(path)[-1])
    np.testing.assert_allclose(traj.velocities_rad_s[0], v0, atol=1e-12)
    assert np.all(traj.velocities_rad_s[-1] == 0.0)
    assert np.all(np.abs(traj.velocities_rad_s) <= vmax * (1 + LIMIT_TOL))
    assert np.all(np.abs(traj.accelerations_rad_s2) <= amax * (1 + LIMIT_TOL))
    w, a = finite_differences(t, q, v0)
    assert np.all(np.abs(w) <= vmax * (1 + LIMIT_TOL))
    assert np.all(np.abs(a) <= amax * (1 + LIMIT_TOL))
    if consistency is not None:
        # the published values belong to the positions: mean of the ends ≈ segment velocity,
        # published acceleration ≈ the finite difference (smooth paths, dense points)
        mean_v = 0.5 * (traj.velocities_rad_s[1:] + traj.velocities_rad_s[:-1])
        assert np.all(np.abs(mean_v - w) <= consistency * vmax)
        assert np.median(np.abs(traj.accelerations_rad_s2 - a) / amax) <= consistency
    if dense:
        assert np.max(np.abs(np.diff(q, axis=0))) <= np.radians(0.5) + 1e-12


def toppra_duration_s(path, vmax, amax):
    """
    Return the TOPP-RA duration of the same samples, s.

    TOPP-RA on a cubic spline through the samples (chord-length parameter), on a grid 16
    times finer than the samples.
    """
    import toppra
    import toppra.algorithm
    import toppra.constraint
    toppra.setup_logging("WARNING")
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    spline = toppra.SplineInterpolator(s, path)
    cons = [toppra.constraint.JointVelocityConstraint(np.stack([-vmax, vmax], axis=1)),
            toppra.constraint.JointAccelerationConstraint(
                np.stack([-amax, amax], axis=1),
                discretization_scheme=toppra.constraint.DiscretizationType.Interpolation)]
    algo = toppra.algorithm.TOPPRA(cons, spline, gridpoints=np.linspace(0.0, s[-1], 16 * len(path) + 1),
                                   parametrizer="ParametrizeConstAccel")
    return algo.compute_trajectory(0.0, 0.0).duration


# ================================================================== dynamics
def bodies_world(robot, q_full, body_pos):
    """Return the centres (K, 4, 2) of body, link 1, 2, 3 and their angles (K, 4)."""
    pts = arm_points(robot, q_full) + body_pos[:, None, :]
    centres = np.concatenate([pts[:, :1], 0.5 * (pts[:, :-1] + pts[:, 1:])], axis=1)
    phi = np.cumsum(q_full, axis=1)
    return centres, np.concatenate([phi[:, :1], phi], axis=1)


def mass_table(mp):
    """Return the masses and inertias of body, link 1, 2, 3."""
    m = np.array([mp.body_mass_kg, *mp.link_masses_kg])
    inertia = np.array([mp.body_inertia_kgm2, *mp.link_inertias_kgm2])
    return m, inertia


def momentum_fd(robot, mp, q_full, body_pos, dt):
    """
    Return the angular momentum about the CoM at the interior samples, by central differences.

    Returns (h, scale: the sum of the terms' magnitudes, the CoM (K, 2)); samples ``dt`` apart.
    """
    m, inertia = mass_table(mp)
    c, ang = bodies_world(robot, q_full, body_pos)
    com = np.einsum("b,kbd->kd", m, c) / m.sum()
    v = (c[2:] - c[:-2]) / (2 * dt)
    w = (ang[2:] - ang[:-2]) / (2 * dt)
    vcom = (com[2:] - com[:-2]) / (2 * dt)
    r = c[1:-1] - com[1:-1, None]
    vr = v - vcom[:, None]
    terms = m * (r[..., 0] * vr[..., 1] - r[..., 1] * vr[..., 0])
    h = terms.sum(axis=1) + (inertia * w).sum(axis=1)
    scale = np.abs(terms).sum(axis=1) + np.abs(inertia * w).sum(axis=1)
    return h, scale, com


def wheel_load(robot, mp, q, qd, qdd, eps=1e-3):
    """Return the wheel's momentum −h and torque −dh/dt per point, from the joint points by finite differences."""
    m, inertia = mass_table(mp)

    def centres(qf):
        return bodies_world(robot, qf, np.zeros((len(qf), 2)))[0]

    c = centres(q)
    v = (centres(q + eps * qd) - centres(q - eps * qd)) / (2 * eps)
    a = ((centres(q + eps * qdd) - centres(q - eps * qdd)) / (2 * eps)
         + (centres(q + eps * qd) - 2 * c + centres(q - eps * qd)) / eps ** 2)
    w = np.concatenate([np.cumsum(qd, axis=1)[:, :1], np.cumsum(qd, axis=1)], axis=1)
    al = np.concatenate([np.cumsum(qdd, axis=1)[:, :1], np.cumsum(qdd, axis=1)], axis=1)

    def rel(x):
        return x - (np.einsum("b,kbd->kd", m, x) / m.sum())[:, None]

    def cross(x, y):
        return x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]

    h = (m * cross(rel(c), rel(v))).sum(axis=1) + (inertia * w).sum(axis=1)
    dh = (m * cross(rel(c), rel(a))).sum(axis=1) + (inertia * al).sum(axis=1)
    return -h, -dh


def simulate_free_floating(robot, mp, path, sub=4):
    """
    Step the arm along the path with the spacecraft free.

    At each step the attitude increment that makes the step's angular momentum about the
    CoM zero (momentum from the joint points, midpoint rule, secant solve); the body moves
    so the CoM stays put.  Returns the full configurations (K, 3) and the body positions
    (K, 2).
    """
    m, inertia = mass_table(mp)

    def rel_centres(qf):
        c, ang = bodies_world(robot, qf[None, :], np.zeros((1, 2)))
        com = m @ c[0] / m.sum()
        return c[0] - com, ang[0]

    def step_momentum(qa, qb):
        ra, aa = rel_centres(qa)
        rb, ab = rel_centres(qb)
        mid, d = 0.5 * (ra + rb), rb - ra
        return float(m @ (mid[:, 0] * d[:, 1] - mid[:, 1] * d[:, 0]) + inertia @ (ab - aa))

    full = robot.full(path)
    fine = np.vstack([np.linspace(a, b, sub, endpoint=False) for a, b in zip(full[:-1], full[1:])] + [full[-1:]])
    q = fine.copy()
    for k in range(len(q) - 1):
        qa = q[k]
        qb = fine[k + 1].copy()
        qb[0] = qa[0]
        d0, d1 = 0.0, 1e-3
        h0 = step_momentum(qa, qb)
        for _ in range(4):                      # secant on the attitude increment
            qb1 = qb.copy()
            qb1[0] = qa[0] + d1
            h1 = step_momentum(qa, qb1)
            if h1 == h0:
                break
            d0, d1, h0 = d1, d1 - h1 * (d1 - d0) / (h1 - h0), h1
        q[k + 1] = qb
        q[k + 1, 0] = qa[0] + d1
    c, _ = bodies_world(robot, q, np.zeros((len(q), 2)))
    com = np.einsum("b,kbd->kd", m, c) / m.sum()
    return q[::sub], (com[0] - com)[::sub]


# ---------------------------------------------------------------- the controller's motion
def quintic_acceleration_peaks(t, q, v, a):
    """
    Return per joint (n,) the largest |acceleration| of the quintic Hermite through the points, exact.

    SciPy's BPoly.from_derivatives as a PPoly: its second derivative at the knots and where the
    third derivative vanishes (``PPoly.roots``), not sampled.
    """
    t, q = np.asarray(t, float), np.asarray(q, float)
    peaks = []
    for j in range(q.shape[1]):
        pp = PPoly.from_bernstein_basis(BPoly.from_derivatives(t, np.stack([q[:, j], v[:, j], a[:, j]], axis=1)))
        roots = pp.derivative(3).roots(extrapolate=False)
        at = np.concatenate([t, roots[np.isfinite(roots)]])
        peaks.append(float(np.max(np.abs(pp.derivative(2)(at)))))
    return np.array(peaks)


def controller_interpolation(t, q, v=None, a=None):
    """
    Return f(times) → (positions, velocities, accelerations), each (K, n), built without sample_points.

    Per joint: a quintic Hermite (BPoly.from_derivatives) with accelerations, a cubic Hermite
    (CubicHermiteSpline) with velocities, np.interp with positions only; the first point held
    before, the last after, at rest (at the last point's time: that point).
    """
    t, q = np.asarray(t, float), np.asarray(q, float)
    n = q.shape[1]
    if a is not None:
        polys = [BPoly.from_derivatives(t, np.stack([q[:, j], v[:, j], a[:, j]], axis=1)) for j in range(n)]
    elif v is not None:
        polys = [CubicHermiteSpline(t, q[:, j], v[:, j]) for j in range(n)]
    else:
        polys = None

    def f(ts):
        ts = np.atleast_1d(np.asarray(ts, float))
        if len(t) == 1:
            pos = np.tile(q[0], (len(ts), 1))
            vel, acc = np.zeros_like(pos), np.zeros_like(pos)
        elif polys is None:
            pos = np.stack([np.interp(ts, t, q[:, j]) for j in range(n)], axis=1)
            k = np.clip(np.searchsorted(t, ts, side="right") - 1, 0, len(t) - 2)
            vel = (q[k + 1] - q[k]) / (t[k + 1] - t[k])[:, None]
            acc = np.zeros_like(pos)
        else:
            tc = np.clip(ts, t[0], t[-1])
            pos = np.stack([p(tc) for p in polys], axis=1)
            vel = np.stack([p(tc, 1) for p in polys], axis=1)
            acc = np.stack([p(tc, 2) for p in polys], axis=1)
        out = (ts < t[0]) | (ts > t[-1])
        vel[out], acc[out] = 0.0, 0.0
        pos[ts < t[0]], pos[ts > t[-1]] = q[0], q[-1]
        end = ts == t[-1]
        vel[end] = 0.0 if v is None else v[-1]
        acc[end] = 0.0 if a is None else a[-1]
        return pos, vel, acc
    return f


def controller_motion(traj, n_samples):
    """(positions, velocities, accelerations), each (n_samples, dof): the controller's motion, evenly over time."""
    t = np.asarray(traj.times_s, float)
    f = controller_interpolation(t, traj.positions_rad, traj.velocities_rad_s, traj.accelerations_rad_s2)
    return f(np.linspace(t[0], t[-1], n_samples))


def controller_wheel_load(scenario, traj, n_samples):
    """(h, tau) of the wheels, (n_samples,) each: :func:`wheel_load` of :func:`controller_motion`."""
    robot = scenario.robot
    q, v, a = controller_motion(traj, n_samples)
    idx = list(robot.planned_joints)
    qd, qdd = np.zeros((len(q), robot.n_joints)), np.zeros((len(q), robot.n_joints))
    qd[:, idx], qdd[:, idx] = v, a
    return wheel_load(robot, scenario.masses, robot.full(q), qd, qdd)
