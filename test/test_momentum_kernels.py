"""
The spacecraft's momentum sums (numba kernels) against an independent NumPy oracle.

The oracle builds the body and link centres, velocities and accelerations of the planar chain
as stacked arrays (the textbook sums: centre of link k = Σ_{j<k} L_j e_j + L_k/2 e_k, the
angular momentum about the system CoM h = Σ m (r − r̄) × (ṙ − r̄̇) + Σ I φ̇ and its rate), and
the momentum map from a central difference of h in the joint rates (h is linear in them).
"""

import numpy as np
import pytest

from spacerobot_planner.config import load_scenario
from spacerobot_planner.spacecraft import (angular_momentum_Nms, momentum_map, momentum_rate_Nm, wheel_load,
                                           MassProperties)
from pathlib import Path

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
