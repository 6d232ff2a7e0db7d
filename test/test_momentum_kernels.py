"""
The spacecraft's momentum sums (numba kernels) against an independent NumPy oracle.

The oracle builds the body and link centres, velocities and accelerations of the planar chain
as stacked arrays (the textbook sums: centre of link k = Σ_{j<k} L_j e_j + L_k/2 e_k, the
angular momentum about the system CoM h = Σ m (r − r̄) × (ṙ − r̄̇) + Σ I φ̇ and its rate), and
the momentum map from a central difference of h in the joint rates (h is linear in them).
The same sums judge ``published.segment_wheel_peaks`` (the wheels' load of the controller's
quintics, per segment) on SciPy's quintics sampled densely.
"""

import numpy as np
import pytest

from spacerobot_planner.config import load_scenario
from spacerobot_planner.spacecraft import (angular_momentum_Nms, momentum_map, momentum_rate_Nm, wheel_load,
                                           MassProperties)
from spacerobot_planner.published import segment_wheel_peaks
from pathlib import Path
from types import SimpleNamespace

from oracles import controller_interpolation

CONFIG = Path(__file__).resolve().parent.parent / "config"


def _oracle(lengths, m_all, i_all, q, qd, qdd):
    """h, dh/dt of rows (N, n) by stacked arrays."""
    n = q.shape[1]
    phi, phid, phidd = np.cumsum(q, 1), np.cumsum(qd, 1), np.cumsum(qdd, 1)
    e = np.stack([np.cos(phi), np.sin(phi)], -1)
    ep = np.stack([-np.sin(phi), np.cos(phi)], -1)
    r = np.zeros((len(q), n + 1, 2))
    v = np.zeros_like(r)
    a = np.zeros_like(r)
    for k in range(n):
        for j in range(k + 1):
            w = lengths[j] * (0.5 if j == k else 1.0)
            r[:, k + 1] += w * e[:, j]
            v[:, k + 1] += w * phid[:, j, None] * ep[:, j]
            a[:, k + 1] += w * (phidd[:, j, None] * ep[:, j] - phid[:, j, None] ** 2 * e[:, j])
    mt = m_all.sum()

    def rel(x):
        return x - (m_all[None, :, None] * x).sum(1, keepdims=True) / mt

    def cross(x, y):
        return x[..., 0] * y[..., 1] - x[..., 1] * y[..., 0]

    spin = np.column_stack([phid[:, 0], phid])
    spin_rate = np.column_stack([phidd[:, 0], phidd])
    h = (m_all * cross(rel(r), rel(v))).sum(1) + (i_all * spin).sum(1)
    rate = (m_all * cross(rel(r), rel(a))).sum(1) + (i_all * spin_rate).sum(1)
    return h, rate


@pytest.mark.parametrize("name", ["paper_3dof.yaml", "servicer_4joint.yaml", "paper_2dof.yaml"])
def test_momentum_sums_match_the_stacked_oracle(name):
    sc = load_scenario(CONFIG / name)
    robot = sc.robot
    masses = sc.masses if sc.masses is not None else MassProperties(2000.0, 1080.0, *(
        (tuple(30.0 for _ in range(robot.n_joints)), tuple(10.0 for _ in range(robot.n_joints)))))
    n = robot.n_joints
    rng = np.random.default_rng(3)
    q, qd, qdd = rng.uniform(-4, 4, (3, 200, n))
    lengths = np.asarray(robot.link_lengths_m, dtype=float)
    m_all = np.concatenate([[masses.body_mass_kg], masses.link_masses_kg])
    i_all = np.concatenate([[masses.body_inertia_kgm2], masses.link_inertias_kgm2])
    h_o, rate_o = _oracle(lengths, m_all, i_all, q, qd, qdd)
    scale_h, scale_r = np.max(np.abs(h_o)), np.max(np.abs(rate_o))
    h = angular_momentum_Nms(robot, masses, q, qd)
    rate = momentum_rate_Nm(robot, masses, q, qd, qdd)
    assert h.shape == rate.shape == (200,)
    np.testing.assert_allclose(h, h_o, rtol=0, atol=1e-12 * scale_h)
    np.testing.assert_allclose(rate, rate_o, rtol=0, atol=1e-12 * scale_r)
    # leading shapes: a single sample is a scalar, a (2, 100) batch keeps its shape
    assert np.ndim(angular_momentum_Nms(robot, masses, q[0], qd[0])) == 0
    assert abs(angular_momentum_Nms(robot, masses, q[0], qd[0]) - h_o[0]) <= 1e-12 * scale_h
    np.testing.assert_allclose(momentum_rate_Nm(robot, masses, q.reshape(2, 100, n), qd.reshape(2, 100, n),
                                                qdd.reshape(2, 100, n)), rate_o.reshape(2, 100),
                               rtol=0, atol=1e-12 * scale_r)
    # the momentum map: h is linear in the rates, so H's column k is (h(+e_k) − h(−e_k)) / 2
    hm = momentum_map(robot, masses, q)
    assert hm.shape == (200, n)
    for k in range(n):
        unit = np.zeros((200, n))
        unit[:, k] = 1.0
        hp, _ = _oracle(lengths, m_all, i_all, q, unit, qdd)
        hn, _ = _oracle(lengths, m_all, i_all, q, -unit, qdd)
        np.testing.assert_allclose(hm[:, k], (hp - hn) / 2, rtol=0, atol=1e-12 * np.max(np.abs(hp)))
    np.testing.assert_allclose(momentum_map(robot, masses, q[0]), hm[0], rtol=0, atol=0)
    # the wheel load is minus h and minus its rate (the locked joints at rest)
    planned = list(robot.planned_joints)
    hw, tw = wheel_load(robot, masses, q[:, planned], qd[:, planned], qdd[:, planned])
    qd_l, qdd_l = np.zeros_like(qd), np.zeros_like(qdd)
    qd_l[:, planned], qdd_l[:, planned] = qd[:, planned], qdd[:, planned]
    qf = robot.full(q[:, planned])
    h_l, r_l = _oracle(lengths, m_all, i_all, qf, qd_l, qdd_l)
    np.testing.assert_allclose(hw, -h_l, rtol=0, atol=1e-12 * max(1.0, np.max(np.abs(h_l))))
    np.testing.assert_allclose(tw, -r_l, rtol=0, atol=1e-12 * max(1.0, np.max(np.abs(r_l))))


@pytest.mark.parametrize("name,seed", [("servicer_3dof.yaml", 0), ("servicer_3dof.yaml", 1),
                                       ("servicer_4joint.yaml", 2)])
def test_segment_wheel_peaks_are_each_segments_peak_load(name, seed):
    """
    segment_wheel_peaks (the chain's wheel check of the controller's motion): each segment's peak |h|, |dh/dt|.

    Oracle: SciPy's quintics through the points (``oracles.controller_interpolation``) sampled 512
    times per segment, the load by the stacked sums above; the kernel's peak within 1e-4 of that
    (below it by at most 1e-4, above it by no more than a smooth load rises between the samples).  16 samples alone miss
    the peak by more on these segments (the test would catch a kernel without its peak search).
    """
    sc = load_scenario(CONFIG / name)
    robot = sc.robot
    dof = len(robot.planned_joints)
    rng = np.random.default_rng(40 + seed)
    m = 12
    t = rng.uniform(0.0, 30.0) + np.concatenate([[0.0], np.cumsum(rng.uniform(0.3, 1.5, m - 1))])
    amp, w, ph = rng.uniform(0.2, 1.0, dof), rng.uniform(0.5, 2.0, dof), rng.uniform(0, 2 * np.pi, dof)
    q = rng.normal(size=dof) + amp * np.sin(w * t[:, None] + ph)
    v = amp * w * np.cos(w * t[:, None] + ph)
    a = -amp * w ** 2 * np.sin(w * t[:, None] + ph)
    traj = SimpleNamespace(times_s=t, positions_rad=q, velocities_rad_s=v, accelerations_rad_s2=a)
    got = segment_wheel_peaks(robot, sc.masses, traj, 16)
    assert got.shape == (m - 1, 2)
    f = controller_interpolation(t, q, v, a)
    lengths = np.asarray(robot.link_lengths_m, dtype=float)
    m_all = np.r_[sc.masses.body_mass_kg, sc.masses.link_masses_kg]
    i_all = np.r_[sc.masses.body_inertia_kgm2, sc.masses.link_inertias_kgm2]
    planned = list(robot.planned_joints)
    coarse_miss = 0.0
    for k in range(m - 1):
        ts = t[k] + (t[k + 1] - t[k]) * np.linspace(0.0, 1.0, 513)
        pos, vel, acc = f(ts)
        qf = np.tile(robot.full(q[0]), (len(ts), 1))
        qdf, qddf = np.zeros_like(qf), np.zeros_like(qf)
        qf[:, planned], qdf[:, planned], qddf[:, planned] = pos, vel, acc
        load = np.abs(np.stack(_oracle(lengths, m_all, i_all, qf, qdf, qddf), axis=1))      # (513, 2)
        want = load.max(axis=0)
        scale = np.abs(load).max(axis=0) + 1e-12
        assert np.all(got[k] >= want - 1e-4 * scale), f"segment {k}: {got[k]} below the peak {want}"
        # between two of the 513 samples a smooth load rises at most |f''| Δ² / 8 above them
        between = np.abs(np.diff(load, 2, axis=0)).max(axis=0) / 8.0
        assert np.all(got[k] <= want + between + 1e-9 * scale), f"segment {k}: {got[k]} above the peak {want}"
        coarse_miss = max(coarse_miss, float(np.max((want - load[::32].max(axis=0)) / scale)))
    assert coarse_miss > 1e-4
    with pytest.raises(ValueError, match="increase strictly"):
        segment_wheel_peaks(robot, sc.masses, SimpleNamespace(times_s=np.r_[t[:3], t[2], t[4:]], positions_rad=q,
                                                              velocities_rad_s=v, accelerations_rad_s2=a))


def test_a_chains_memo_of_segment_wheel_peaks_gives_each_segment_its_own_peaks():
    """
    Within ``shared_path_models`` (a chain) segment_wheel_peaks keeps each segment's peaks by its row.

    A re-timed trajectory sharing most segments with the last one (here: the same points, one
    point's acceleration and one duration changed, then the points shifted in time by a constant)
    gets, segment for segment, what a call without the memo computes, bit for bit: the changed
    segments their own peaks (a memo keyed without the accelerations or the durations would hand
    them the old ones), the others theirs.
    """
    from spacerobot_planner.trajectory import shared_path_models

    sc = load_scenario(CONFIG / "servicer_3dof.yaml")
    robot = sc.robot
    dof = len(robot.planned_joints)
    rng = np.random.default_rng(77)
    m = 30
    t = np.round(1024 * np.concatenate([[0.0], np.cumsum(rng.uniform(0.3, 1.5, m - 1))])) / 1024   # shifts exact
    amp, w, ph = rng.uniform(0.2, 1.0, dof), rng.uniform(0.5, 2.0, dof), rng.uniform(0, 2 * np.pi, dof)
    q = amp * np.sin(w * t[:, None] + ph)
    v = amp * w * np.cos(w * t[:, None] + ph)
    a = -amp * w ** 2 * np.sin(w * t[:, None] + ph)
    first = SimpleNamespace(times_s=t, positions_rad=q, velocities_rad_s=v, accelerations_rad_s2=a)
    a2 = a.copy()
    a2[7] *= 1.3
    t2 = t.copy()
    t2[20:] += 0.25                                     # segment 19 lasts longer, the later ones move in time
    second = SimpleNamespace(times_s=t2 + 3.0, positions_rad=q, velocities_rad_s=v, accelerations_rad_s2=a2)
    alone = [segment_wheel_peaks(robot, sc.masses, tr) for tr in (first, second)]
    with shared_path_models():
        chained = [segment_wheel_peaks(robot, sc.masses, tr) for tr in (first, second, second)]
    for got, want in zip(chained, alone + alone[1:]):
        np.testing.assert_array_equal(got, want)
    changed = np.flatnonzero(np.any(alone[0] != alone[1], axis=1))
    assert set(changed) == {6, 7, 19}, changed
