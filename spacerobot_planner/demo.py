"""`make demo`: the planning core on the paper's 3-DOF scene (offline, no ROS graph)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .collision import CollisionChecker
from .config import load_scenario
from .cspace import build_cspace
from .ik import capture_posture, grasp_ik


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--params-file", default=str(Path(__file__).resolve().parent.parent
                                                 / "config" / "paper_3dof.yaml"))
    ap.add_argument("--out", default="out", help="folder for figures")
    args = ap.parse_args(argv)
    sc = load_scenario(args.params_file)
    deg = np.degrees
    print(f"scene: {args.params_file}")
    print(f"robot: joints {sc.robot.joint_names}, planned {sc.robot.planned_names}, "
          f"links {sc.robot.link_lengths_m} m")
    chk = CollisionChecker(sc.robot, sc.scene)
    print(f"start {np.round(deg(sc.start_rad), 2)} deg: clearance {chk.clearance_m(sc.start_rad):.3f} m")
    cp = capture_posture(sc.robot, sc.scene.target)
    print(f"capture posture (max manipulability {cp.manipulability:.3f} m^2): "
          f"{np.round(deg(cp.q_full), 2)} deg, tip {np.round(cp.tip_m, 3)} m")
    for i, s in enumerate(grasp_ik(sc.robot, sc.scene)):
        print(f"IK branch {i}: {np.round(deg(s.q_full), 2)} deg, w={s.manipulability:.3f} m^2, "
              f"clearance {s.clearance_m:.3f} m")
    build_cspace(sc.robot, sc.scene, sc.grid)   # JIT warm-up
    cs = build_cspace(sc.robot, sc.scene, sc.grid)
    print(f"C-space {cs.grid.label()}: {100 * cs.free_fraction:.1f} % free, built in "
          f"{1e3 * cs.seconds:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
