"""
Steepest descent of the potential phi = -log u over the grid's face neighbours.

From the start node, repeatedly move to the face neighbour with the largest
``log_u`` (wrap-around on periodic axes, walls beyond bounded axes) provided it
is *strictly* larger than the current node's value; ties between neighbours go
to the first in the fixed order ``(axis 0, -1), (axis 0, +1), (axis 1, -1),
...``.  Stops at a goal node.  Since every step strictly increases log u, no
node repeats and the walk ends after at most (number of nodes) steps.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from .field import Field, bfs_distance
from .field.graph import grid_strides
from .collision import NO_REFCOUNT
from .motion import motion_scratch, segment_free_from

# status codes of the kernels
_REACHED, _STUCK, _TOO_LONG, _BLOCKED, _JOINED = 0, 1, 2, 3, 4
#: A blocked walk looks for a detour within this many index steps per axis.
DETOUR_STEPS = 1


@dataclass(frozen=True)
class GridPath:
    """
    A walk over grid nodes.

    nodes : int64 array (m, ndim), start node first; the goal node last when
        ``reached``, else the node where the walk stopped.
    reached : whether the walk ended on a goal node.
    steps : number of moves (m - 1).
    reason : None when reached, else why not.
    blocked : the walk stopped at a node whose strictly higher neighbours all fail the
        motion test (only with a ``motions`` test; see :func:`descend`).
    """

    nodes: np.ndarray
    reached: bool
    steps: int
    reason: str | None
    blocked: bool = False


@nb.njit(cache=True, nogil=True, inline="always")
def _along(c, d, n, periodic):
    """Index c + d along an axis of n nodes: wrapped on a periodic axis, -1 beyond a wall."""
    k = c + d
    if k < 0 or k >= n:
        if not periodic:
            return -1
        k %= n
    return k


@nb.njit(cache=True, nogil=True, inline="always")
def _steepest_neighbour(log_u_flat, f, shape, strides, periodic):
    """
    Return the steepest strictly higher face neighbour of ``f``, else -1.

    Flat index of the face neighbour of node ``f`` with the largest log u, if it is strictly larger
    than log u at ``f`` (ties: first in the fixed order), else -1.
    """
    best = log_u_flat[f]
    out = -1
    for a in range(shape.size):
        c = (f // strides[a]) % shape[a]
        for step in (-1, 1):
            nc = _along(c, step, shape[a], periodic[a])
            if nc < 0:
                continue
            g = f + (nc - c) * strides[a]
            if log_u_flat[g] > best:
                best = log_u_flat[g]
                out = g
    return out


@nb.njit(cache=True, nogil=True)
def _ascend(log_u_flat, is_goal_flat, shape, periodic, f, out):
    """
    Walk from flat node ``f``; ``out`` receives the flat nodes visited.

    Returns (number of nodes, status).
    """
    strides = grid_strides(shape)
    m = 0
    out[m] = f
    m += 1
    while True:
        if is_goal_flat[f]:
            return m, _REACHED
        if m >= out.size:
            return m, _TOO_LONG
        f = _steepest_neighbour(log_u_flat, f, shape, strides, periodic)
        if f < 0:
            return m, _STUCK
        out[m] = f
        m += 1


@nb.njit(**NO_REFCOUNT)
def _detour(log_u_flat, shape, periodic, strides, f, radius, lower, step, q_template, planned, lengths,
            checked, body, verts, starts, obs_centres, obs_radii, threshold_m, seg_step_rad, reach_m, q_full, pts,
            body_w, path, box_nodes, off, c0, qa, qb, clr_ends):
    """
    Search breadth-first for a detour to a higher node.

    Breadth-first over motions that pass, within ``radius`` index steps of node ``f`` per axis, to
    the nearest node whose log u is strictly above f's.

    Writes the nodes after f up to it into ``path`` and returns their count (0: none).  Scratch
    (:func:`_walk_valid`'s): box_nodes int64 (3, (2 radius + 1)^ndim) (each box node's parent, flat
    node and the queue), off and c0 int64 (ndim,), qa and qb (ndim,), clr_ends (2,).
    """
    ndim = shape.size
    side = 2 * radius + 1
    box = 1
    for a in range(ndim):
        box *= side
    parent = box_nodes[0]
    flat_of = box_nodes[1]
    queue = box_nodes[2]
    for t in range(box):
        parent[t] = -2                          # -2 unseen; box index of the parent
    for a in range(ndim):
        off[a] = 0
    for a in range(ndim):
        c0[a] = (f // strides[a]) % shape[a]
    centre = 0
    for a in range(ndim):
        centre = centre * side + radius
    parent[centre] = -1
    flat_of[centre] = f
    queue[0] = centre
    head, tail = 0, 1
    here = log_u_flat[f]
    while head < tail:
        bi = queue[head]
        head += 1
        rem = bi
        for a in range(ndim - 1, -1, -1):
            off[a] = rem % side - radius
            rem //= side
        g = flat_of[bi]
        for a in range(ndim):
            qa[a] = lower[a] + ((c0[a] + off[a]) % shape[a] if periodic[a] else c0[a] + off[a]) * step[a]
        clr_ends[0] = np.nan                    # the clearance at qa: measured by the node's first test
        for a in range(ndim):
            for d in (-1, 1):
                o = off[a] + d
                if o < -radius or o > radius:
                    continue
                k = _along(c0[a], o, shape[a], periodic[a])
                if k < 0:
                    continue
                nb_box = bi + d * side ** (ndim - 1 - a)
                if parent[nb_box] != -2:
                    continue
                kc = (g // strides[a]) % shape[a]
                h = g + (k - kc) * strides[a]
                if not log_u_flat[h] > -np.inf:
                    continue
                for b in range(ndim):
                    qb[b] = qa[b]
                qb[a] += d * step[a]
                if not segment_free_from(qa, qb, q_template, planned, lengths, checked, body, verts, starts,
                                         obs_centres, obs_radii, threshold_m, seg_step_rad, reach_m, q_full, pts,
                                         body_w, clr_ends):
                    continue
                parent[nb_box] = bi
                flat_of[nb_box] = h
                if log_u_flat[h] > here:
                    n = 0
                    t = nb_box
                    while t != centre:
                        n += 1
                        t = parent[t]
                    t = nb_box
                    for i in range(n - 1, -1, -1):
                        path[i] = flat_of[t]
                        t = parent[t]
                    return n
                queue[tail] = nb_box
                tail += 1
    return 0


@nb.njit(cache=True, nogil=True)
def _ascend_valid(log_u_flat, is_goal_flat, shape, periodic, f, out, lower, step, detour_steps, owner, walk, stood,
                  q_template, planned, lengths, checked, body, verts, starts, obs_centres, obs_radii, threshold_m,
                  seg_step_rad, reach_m):
    """
    Walk as :func:`_ascend` does, but only along motions that pass the motion test.

    The walk of :func:`_ascend`, but each step to the steepest strictly higher neighbour whose
    straight segment passes ``motion.segment_free`` (next steepest if not); where none passes, a
    detour over passing motions within ``detour_steps`` to the nearest strictly higher node (log u
    rises from detour to detour, so the walk ends).  A step ends at the neighbour node's own
    coordinates (not across a seam), so the clearance measured there starts the next step's
    test (``motion.segment_free_from``): each node is measured once.

    ``owner`` int64 (nodes,) or empty: the nodes earlier walks on the same field stood on (a
    detour's inner nodes are passed, not stood on), each as ``walk * nodes + position`` in that
    walk, -1 where none (:class:`WalkJoins`).  A walk stands on a node as a pure function of the
    node, so where this one stands on such a node it goes on as that walk did: it stops there
    (status ``_JOINED``, the node its last) and the caller takes the rest from that walk.  The
    nodes it stands on are written as walk ``walk``'s.  ``stood`` int64 (nodes,) or empty: the
    positions in ``out`` of the nodes the walk stood on, in order (so that a first walk, run
    without ``owner``, can be written there later).

    Returns (number of nodes, status, number of nodes stood on (0 without ``stood``)).
    :func:`_walk_valid` with its scratch.
    """
    ndim = shape.size
    box = (2 * detour_steps + 1) ** ndim
    q_full, pts, body_w = motion_scratch(q_template, lengths, body)
    return _walk_valid(log_u_flat, is_goal_flat, shape, periodic, f, out, lower, step, detour_steps, owner, walk,
                       stood, q_template, planned, lengths, checked, body, verts, starts, obs_centres, obs_radii,
                       threshold_m, seg_step_rad, reach_m, grid_strides(shape), q_full, pts, body_w, np.empty(ndim),
                       np.empty(ndim), np.empty(ndim, np.int64), np.empty((4, 2 * ndim), np.int64), np.empty(2 * ndim),
                       np.empty(box, np.int64), np.empty(2), np.empty((3, box), np.int64), np.empty(ndim, np.int64),
                       np.empty(ndim, np.int64))


@nb.njit(**NO_REFCOUNT)
def _walk_valid(log_u_flat, is_goal_flat, shape, periodic, f, out, lower, step, detour_steps, owner, walk, stood,
                q_template, planned, lengths, checked, body, verts, starts, obs_centres, obs_radii, threshold_m,
                seg_step_rad, reach_m, strides, q_full, pts, body_w, qa, qb, coord, cand, cand_v, detour, clr_ends,
                box_nodes, off, c0):
    """
    Run :func:`_ascend_valid` with the grid's strides and the scratch given.

    Scratch past the motion test's (``motion.motion_scratch``): qa, qb (ndim,), coord int64 (ndim,),
    the candidates int64 (4, 2 ndim) (flat node, axis, direction, index along the axis), their log u
    (2 ndim,), the detour's nodes int64 (box,), clr_ends (2,), the detour's box nodes int64 (3, box),
    off and c0 int64 (ndim,); box = (2 detour_steps + 1)^ndim.
    """
    ndim = shape.size
    cand_f = cand[0]
    cand_a = cand[1]
    cand_d = cand[2]
    cand_n = cand[3]
    clr_ends[0] = np.nan                 # [0] the clearance at the current node once measured; [1] the next
    clr_ends[1] = np.nan
    m = 0
    out[m] = f
    m += 1
    joins = owner.size > 0
    keep = stood.size > 0
    s = 0
    while True:
        if is_goal_flat[f]:
            return m, _REACHED, s
        if m >= out.size:
            return m, _TOO_LONG, s
        if joins:
            if owner[f] >= 0:
                return m, _JOINED, s     # an earlier walk stood here: the rest is its
            owner[f] = walk * owner.size + m - 1
        if keep:
            stood[s] = m - 1
            s += 1
        here = log_u_flat[f]
        k = 0
        for a in range(ndim):
            coord[a] = (f // strides[a]) % shape[a]
            qa[a] = lower[a] + coord[a] * step[a]
        for a in range(ndim):
            c = coord[a]
            for d in (-1, 1):
                nc = _along(c, d, shape[a], periodic[a])
                if nc < 0:
                    continue
                g = f + (nc - c) * strides[a]
                v = log_u_flat[g]
                if not v > here:
                    continue
                t = k                    # insertion by value, ties keep the fixed order
                while t > 0 and cand_v[t - 1] < v:
                    cand_f[t], cand_v[t] = cand_f[t - 1], cand_v[t - 1]
                    cand_a[t], cand_d[t], cand_n[t] = cand_a[t - 1], cand_d[t - 1], cand_n[t - 1]
                    t -= 1
                cand_f[t], cand_v[t], cand_a[t], cand_d[t], cand_n[t] = g, v, a, d, nc
                k += 1
        if k == 0:
            return m, _STUCK, s
        moved = False
        for t in range(k):
            for a in range(ndim):
                qb[a] = qa[a]
            a = cand_a[t]
            seam = cand_n[t] != coord[a] + cand_d[t]
            if seam:
                qb[a] += cand_d[t] * step[a]             # the short way across a seam
            else:
                qb[a] = lower[a] + cand_n[t] * step[a]   # the neighbour node itself
            if segment_free_from(qa, qb, q_template, planned, lengths, checked, body, verts, starts, obs_centres,
                                 obs_radii, threshold_m, seg_step_rad, reach_m, q_full, pts, body_w, clr_ends):
                f = cand_f[t]
                out[m] = f
                m += 1
                moved = True
                clr_ends[0] = np.nan if seam else clr_ends[1]    # measured at the next node's own coordinates
                break
        if not moved:
            n = 0 if detour_steps == 0 else _detour(
                log_u_flat, shape, periodic, strides, f, detour_steps, lower, step, q_template,
                planned, lengths, checked, body, verts, starts, obs_centres, obs_radii, threshold_m,
                seg_step_rad, reach_m, q_full, pts, body_w, detour, box_nodes, off, c0, qa, qb, clr_ends)
            if n == 0 or m + n > out.size:
                return m, _BLOCKED, s
            for i in range(n):
                out[m] = detour[i]
                m += 1
            f = detour[n - 1]
            clr_ends[0] = np.nan


class WalkJoins:
    """
    The walks taken on one field with one motion test, for later walks to join (:func:`descend`'s ``joins``).

    A walk stands on a node (its start, each step's end, each detour's end) and goes on from it as
    a pure function of that node: a later walk from another start that stands on a node an earlier
    one stood on goes on as that one did.  So it stops there and takes the rest of the earlier
    walk's path, the path it would have walked (a plan whose every start node's walk is blocked
    walks each one into the same blocked node: eight walks of about 0.25 ms each before a repair,
    measured on the repairing scenes of ``bench scenes --dof 3``).  ``owner`` int64 (nodes,): each
    node an earlier walk stood on as ``walk * nodes + position``, -1 elsewhere, made for the second
    walk (None before: a plan whose first walk reaches the goal, most of them, and a replan from a
    cached walk make none; at 120³ it is 14 MB); ``walks``: each walk's flat nodes (int64), its
    kernel's status and the positions of the nodes it stood on.  For one field and one motion test
    only: a walk on another field or with another test goes elsewhere.
    """

    def __init__(self, field: Field):
        """Hold no walk yet, for walks on ``field``."""
        self.field = field
        self.owner = None
        self.walks = []

    def owners(self) -> np.ndarray:
        """Return :attr:`owner`, made from the walks so far where it is not made yet."""
        if self.owner is None:
            n = np.asarray(self.field.log_u).size
            self.owner = np.full(n, -1, np.int64)
            for w, (flat, _, stood) in enumerate(self.walks):     # one walk: none joined another yet
                at = flat[stood]
                free = self.owner[at] < 0
                self.owner[at[free]] = w * n + stood[free]
        return self.owner

    def rest(self, flat):
        """
        Return ``(flat nodes, status)`` of a walk that stopped on a node an earlier walk stood on (its last).

        flat: its flat nodes (int64), up to that node; the earlier walk's nodes from there on and its
        kernel's status follow.
        """
        earlier, pos = divmod(int(self.owner[flat[-1]]), self.owner.size)
        before, status, _ = self.walks[earlier]
        return np.concatenate([flat[:-1], before[pos:]]), status


#: :func:`_ascend_valid`'s ``owner`` and ``stood`` without joins.
_NO_OWNER = np.zeros(0, np.int64)


def descend(field: Field, start_node, motions=None, lower_rad=None, step_rad=None,
            detour_steps: int = DETOUR_STEPS, joins: WalkJoins | None = None) -> GridPath:
    """
    Steepest descent of phi (ascent of ``field.log_u``) from ``start_node``.

    start_node : int sequence of length ndim (grid node index).
    motions : optional ``motion.SegmentTest``; then each step goes to the steepest strictly
        higher neighbour whose straight segment passes it (the next steepest otherwise),
        with nodes at ``lower_rad + index * step_rad`` (per axis, rad).  Without it, or
        when every step passes, the walk is plain steepest descent.  Where no higher
        neighbour's motion passes, the walk looks for a detour over passing motions within
        ``detour_steps`` index steps to the nearest strictly higher node (0: none).
    joins : optional :class:`WalkJoins` of ``field`` (with ``motions`` and the same
        ``detour_steps`` each call): the walk stops where it stands on a node an earlier walk
        stood on and takes the rest of that walk's path (the same path), and is kept there for
        the walks after it.
    Returns a :class:`GridPath`; ``reason`` says why the goal was not reached
    ("start node is an obstacle", "start node not connected to the goal",
    "stuck at node (i, j): no strictly higher neighbour").
    Raises ValueError if ``start_node`` has the wrong length or lies outside
    the grid.
    """
    log_u = np.ascontiguousarray(field.log_u, dtype=np.float64)
    shape = log_u.shape
    start = np.asarray(start_node)
    if start.shape != (len(shape),):
        raise ValueError(f"start_node: expected {len(shape)} indices, got {start.tolist()}")
    if not np.issubdtype(start.dtype, np.integer):
        if not np.all(start == np.round(start)):
            raise ValueError(f"start_node: node indices must be integers, got {start.tolist()}")
    start = start.astype(np.int64)
    if np.any(start < 0) or np.any(start >= np.array(shape)):
        raise ValueError(f"start_node: {tuple(start.tolist())} lies outside the grid {shape}")
    node = tuple(int(s) for s in start)
    if field.occupied[node]:
        return GridPath(start.reshape(1, -1), False, 0, "start node is an obstacle")
    is_goal = field.goal_mask
    if not np.isfinite(log_u[node]) and not is_goal[node]:
        dist = bfs_distance(field.occupied, field.periodic, field.goal_nodes)
        if dist[node] < 0:
            return GridPath(start.reshape(1, -1), False, 0, "start node not connected to the goal")
        return GridPath(start.reshape(1, -1), False, 0,
                        f"stuck at node {node}: flat field (u = 0 in float64), no strictly higher neighbour")
    out = np.empty(log_u.size, np.int64)
    flat0 = int(np.ravel_multi_index(node, shape))
    if motions is None:
        m, status = _ascend(log_u.ravel(), is_goal.ravel(), np.array(shape, np.int64),
                            np.array(field.periodic, np.bool_), flat0, out)
    else:
        if joins is not None and joins.field is not field:
            raise ValueError("joins: the walks of another field")
        walk = 0 if joins is None else len(joins.walks)
        stood = _NO_OWNER if joins is None else np.empty(log_u.size, np.int64)

        def walked(owner):
            return _ascend_valid(log_u.ravel(), is_goal.ravel(), np.array(shape, np.int64),
                                 np.array(field.periodic, np.bool_), flat0, out, np.asarray(lower_rad, dtype=float),
                                 np.asarray(step_rad, dtype=float), int(detour_steps), owner, walk, stood,
                                 *motions.arrays())
        m, status, s = walked(joins.owners() if walk else _NO_OWNER)     # the first walk: none to join
        if joins is not None:
            flat = out[:m].copy()
            if status == _JOINED:
                flat, status = joins.rest(flat)
                if flat.size + (2 * int(detour_steps) + 1) ** len(shape) >= out.size:
                    # near the walk's room (detours can pass nodes twice): alone, the walk could have
                    # stopped for room where the joined one did not; walked alone, it is the walk
                    m, status, s = walked(_NO_OWNER)
                    flat = out[:m].copy()
            joins.walks.append((flat, status, stood[:s].copy()))
            return _grid_path(flat, status, shape)
    return _grid_path(out[:m], status, shape)


def _grid_path(flat, status, shape) -> GridPath:
    """Return the :class:`GridPath` of a walk's flat nodes (int64) that ended with ``status``."""
    m = flat.size
    nodes = np.stack(np.unravel_index(flat, shape), axis=1).astype(np.int64)
    if status == _REACHED:
        return GridPath(nodes, True, m - 1, None)
    last = tuple(int(x) for x in nodes[-1])
    if status == _STUCK:
        return GridPath(nodes, False, m - 1, f"stuck at node {last}: no strictly higher neighbour")
    if status == _BLOCKED:
        return GridPath(nodes, False, m - 1, f"blocked at node {last}: the straight segment to every "
                        "strictly higher neighbour collides", blocked=True)
    return GridPath(nodes, False, m - 1, f"step limit {int(np.prod(shape))} reached at node {last}")


@nb.njit(cache=True, nogil=True)
def _successors(log_u_flat, shape, periodic):
    """
    Return every node's steepest strictly-higher face neighbour, -1 where none.

    Flat index of the steepest strictly-higher face neighbour of every node (the walk's rule and tie
    order), -1 where there is none.
    """
    strides = grid_strides(shape)
    succ = np.full(log_u_flat.size, -1, np.int64)
    for f in range(log_u_flat.size):
        if log_u_flat[f] > -np.inf:
            succ[f] = _steepest_neighbour(log_u_flat, f, shape, strides, periodic)
    return succ


@nb.njit(cache=True, nogil=True)
def _resolve(succ, goal_flat):
    """1 where following ``succ`` ends on a goal node, else 0."""
    n = succ.size
    state = np.zeros(n, np.int8)          # 0 unknown, 1 reaches goal, 2 does not
    for g in goal_flat:
        state[g] = 1
    chain = np.empty(n, np.int64)
    for f in range(n):
        m = 0
        x = f
        while state[x] == 0 and succ[x] >= 0:
            chain[m] = x
            m += 1
            x = succ[x]
        result = state[x] if state[x] != 0 else 2
        if state[x] == 0:
            state[x] = 2
        for t in range(m):
            state[chain[t]] = result
    return state == 1


def reaches_goal_mask(field: Field) -> np.ndarray:
    """
    Return where descent reaches the goal, a bool array of the grid shape.

    True at every node from which :func:`descend` reaches the goal (all nodes at once, linear time).
    """
    log_u = np.ascontiguousarray(field.log_u, dtype=np.float64)
    succ = _successors(log_u.ravel(), np.array(log_u.shape, np.int64), np.array(field.periodic, np.bool_))
    goal_flat = np.ravel_multi_index(tuple(field.goal_nodes.T), log_u.shape).astype(np.int64)
    ok = _resolve(succ, goal_flat).reshape(log_u.shape)
    ok[field.occupied] = False
    return ok
