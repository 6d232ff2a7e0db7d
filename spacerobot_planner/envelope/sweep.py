"""
The sweep's work: the pose grid, its chunks, and one chunk planned into rows.

A capture envelope plans the grasp of the scene's target at every pose of a grid: the
target body's centre ``(x_m, y_m)`` and yaw, from one or several start postures.  Poses are
numbered ``pose_id = ((i_yaw · NY + i_y) · NX + i_x) · NS + i_start``: the starts of one
target pose are neighbours, so one planner serves them from the same C-space and field.

:func:`plan_chunk` is one task: it builds one ``Planner`` for its poses (the spacecraft-body
table is kept across target moves; the C-space and the field are per target pose) and plans
each pose with :func:`~spacerobot_planner.offline.plan_offline`, the pipeline of a single
``spacerobot-plan`` run, its goal the grasp of that pose's target (a ``scenario.goal_deg``
does not apply).  A pose whose planning raises becomes a row with code ``internal_error``
and the reason; the chunk goes on.

No rclpy, no Dask here (``engine.py`` runs the chunks).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..offline import plan_offline
from ..planner import Planner
from ..problem import Scenario
from ..results import Code
from ..scene import Target

__all__ = ["PoseGrid", "Pose", "COLUMNS", "TIMING_COLUMNS", "plan_chunk", "plan_pose", "chunks", "axis_values",
           "blank_row"]

#: the row's columns and their types, in the order of ``envelope.csv``
COLUMNS = (
    ("pose_id", int),              # the pose's number (see the module docstring)
    ("x_m", float),                # the target body's centre, planning frame, m
    ("y_m", float),
    ("yaw_deg", float),            # the target's yaw, deg
    ("start_index", int),          # which start posture (``--starts-deg``, in order; 0: the scenario's)
    ("code", str),                 # the result code (README, "Result codes")
    ("path_length_rad", float),    # joint-space length of the path (nan without path)
    ("min_clearance_m", float),    # the certified path's clearance (nan without path)
    ("plan_s", float),             # wall time of this pose's pipeline in its worker, s (varies run to run)
    ("duration_s", float),         # the published trajectory's duration, s (nan without trajectory)
    ("approach_error_deg", float),  # link 3 off the handle's normal at the goal, deg
    ("peak_wheel_momentum_Nms", float),    # the reaction, where the scenario reports one (else nan)
    ("peak_wheel_torque_Nm", float),
    ("free_floating_attitude_change_deg", float),
    ("free_floating_tip_miss_m", float),
    ("goal_deg", str),             # the goal posture (the grasp), planned joints, deg, space-separated
    ("start_deg", str),            # the start posture, deg, space-separated
    ("reason", str),               # why not ok ("" when ok)
)
#: columns that change from run to run (wall times); every other column is a function of the pose
TIMING_COLUMNS = ("plan_s",)


@dataclass(frozen=True)
class Pose:
    """One pose of the grid: the target's centre (m) and yaw (deg), and the start's index."""

    pose_id: int
    x_m: float
    y_m: float
    yaw_deg: float
    start_index: int


def axis_values(lo: float, hi: float, count: int, name: str) -> tuple:
    """
    Return ``count`` values from ``lo`` to ``hi`` inclusive, evenly spaced.

    ValueError naming ``name`` for a count below 1, a non-finite end, or one value asked
    for between two different ends.
    """
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name}: the ends must be finite numbers, got {lo} {hi}")
    if int(count) != count or count < 1:
        raise ValueError(f"{name}: the count must be an integer ≥ 1, got {count}")
    if count == 1 and lo != hi:
        raise ValueError(f"{name}: one value asked for between two different ends ({lo} and {hi}); "
                         "give the same value twice, or a count ≥ 2")
    if count > 1 and lo == hi:
        raise ValueError(f"{name}: {int(count)} values asked for between equal ends ({lo}); "
                         "give a count of 1, or two different ends")
    return tuple(float(v) for v in np.linspace(lo, hi, int(count)))


@dataclass(frozen=True)
class PoseGrid:
    """
    The poses of a sweep.

    Attributes
    ----------
        x_m, y_m: the target centre's coordinates (NX,), (NY,), m.
        yaw_deg: the target's yaws (NA,), deg.
        starts_rad: the start postures, NS tuples of (dof,) planned-joint angles, rad.

    """

    x_m: tuple
    y_m: tuple
    yaw_deg: tuple
    starts_rad: tuple

    def __post_init__(self):
        for name in ("x_m", "y_m", "yaw_deg", "starts_rad"):
            if len(getattr(self, name)) < 1:
                raise ValueError(f"PoseGrid.{name}: at least one value")
        object.__setattr__(self, "starts_rad", tuple(tuple(float(v) for v in s) for s in self.starts_rad))

    @property
    def shape(self) -> tuple:
        """(NA, NY, NX, NS)."""
        return len(self.yaw_deg), len(self.y_m), len(self.x_m), len(self.starts_rad)

    @property
    def n_poses(self) -> int:
        return int(np.prod(self.shape))

    def pose(self, pose_id: int) -> Pose:
        """Return the pose numbered ``pose_id`` (see the module docstring)."""
        if not 0 <= pose_id < self.n_poses:
            raise IndexError(f"pose_id {pose_id} outside 0..{self.n_poses - 1}")
        ia, iy, ix, i_start = np.unravel_index(int(pose_id), self.shape)
        return Pose(int(pose_id), self.x_m[ix], self.y_m[iy], self.yaw_deg[ia], int(i_start))

    def to_json_dict(self) -> dict:
        return {"x_m": list(self.x_m), "y_m": list(self.y_m), "yaw_deg": list(self.yaw_deg),
                "starts_deg": [[math.degrees(v) for v in s] for s in self.starts_rad]}


def chunks(pose_ids, size, group: int = 1) -> list:
    """
    Split ``pose_ids`` (sorted here) into lists of consecutive ids.

    ``size``: poses per chunk, an int (every chunk; the last may be shorter) or a function
    of the ids not yet in a chunk returning the next chunk's size (``engine.guided_size``).
    ``group``: a chunk is extended past its size until it ends on a multiple of ``group``
    ids (the ``NS`` starts of one target pose share its C-space and field, so they stay in
    one chunk); 1 cuts exactly at ``size``.
    """
    ids = sorted(int(i) for i in pose_ids)
    out, k = [], 0
    while k < len(ids):
        n = size if isinstance(size, int) else int(size(len(ids) - k))
        if n < 1:
            raise ValueError(f"chunk size: must be ≥ 1, got {n}")
        end = min(k + n, len(ids))
        while group > 1 and end < len(ids) and ids[end] // group == ids[end - 1] // group:
            end += 1
        out.append(ids[k:end])
        k = end
    return out


def _deg_text(q_rad) -> str:
    return " ".join(f"{v:.6f}" for v in np.degrees(np.asarray(q_rad, dtype=float)))


def blank_row(grid: PoseGrid, pose_id: int) -> dict:
    """Return a row of one pose with no result yet (code ``internal_error``, every metric nan)."""
    p = grid.pose(pose_id)
    row = {name: (math.nan if typ is float else "") for name, typ in COLUMNS}
    row.update(pose_id=p.pose_id, x_m=p.x_m, y_m=p.y_m, yaw_deg=p.yaw_deg, start_index=p.start_index,
               code=str(Code.INTERNAL_ERROR), start_deg=_deg_text(grid.starts_rad[p.start_index]))
    return row


def _num(x) -> float:
    return math.nan if x is None else float(x)


def plan_pose(planner: Planner, scenario: Scenario, grid: PoseGrid, pose_id: int) -> dict:
    """
    Plan one pose with ``planner`` and return its row (``COLUMNS``).

    The planner's scene becomes ``scenario.scene`` with the target moved to the pose; the
    plan goes from the pose's start to the grasp of that target (``offline.plan_offline``).
    Never raises: an exception becomes code ``internal_error`` with the reason.
    """
    t0 = time.perf_counter()
    row = blank_row(grid, pose_id)
    p = grid.pose(pose_id)
    try:
        base = scenario.scene.target
        target = Target(center_m=(p.x_m, p.y_m), yaw_rad=math.radians(p.yaw_deg), body_side_m=base.body_side_m,
                        handle_side_m=base.handle_side_m)
        planner.set_scene(scenario.scene.with_target(target))
        try:
            done = plan_offline(planner, np.asarray(grid.starts_rad[p.start_index]))
        except ValueError as e:             # the drift compensation refuses the scenario
            row.update(code=str(Code.INVALID_INPUT), reason=str(e))
        else:
            _fill(row, done)
    except Exception as e:  # noqa: BLE001 -- a failure of one pose is a row, never the end of the sweep
        row.update(code=str(Code.INTERNAL_ERROR),
                   reason=f"internal error while planning this pose: {type(e).__name__}: {e}")
    row["reason"] = " ".join(str(row["reason"]).split())       # one line per row in the CSV
    row["plan_s"] = time.perf_counter() - t0
    return row


def _fill(row: dict, done) -> None:
    """Copy an ``offline.OfflinePlan``'s figures into a row."""
    res = done.result
    row.update(code=str(res.code), reason=res.reason or "", approach_error_deg=_num(res.approach_error_deg))
    if res.goal_rad is not None:
        row["goal_deg"] = _deg_text(res.goal_rad)
    if len(res.path_rad):
        row.update(path_length_rad=_num(res.path_length_rad), min_clearance_m=_num(res.min_clearance_m))
    if done.processed is not None:
        row["duration_s"] = float(done.processed.dense.duration_s)
    r = res.reaction
    if r is not None:
        row.update(peak_wheel_momentum_Nms=_num(r.peak_wheel_momentum_Nms),
                   peak_wheel_torque_Nm=_num(r.peak_wheel_torque_Nm),
                   free_floating_attitude_change_deg=_num(r.free_floating_attitude_change_deg),
                   free_floating_tip_miss_m=_num(r.free_floating_tip_miss_m))


def plan_chunk(scenario: Scenario, grid: PoseGrid, pose_ids, numba_threads: int | None = None,
               stop=None) -> list:
    """
    Plan the poses ``pose_ids`` with one planner; return their rows, in that order.

    ``numba_threads``: the most threads the planner's parallel kernels use in this process (a
    Dask worker runs one process per core: 1; ``planner.max_threads``), None to leave the
    scenario's setting.  ``stop``: a sequence, or None; once it is not empty no further pose
    is planned (the rows so far are returned: the serial sweep's Ctrl-C).
    """
    extra = {} if numba_threads is None else {"max_threads": max(1, int(numba_threads))}
    planner = Planner(scenario, reaction=True, **extra)
    rows = []
    for i in pose_ids:
        if stop:
            break
        rows.append(plan_pose(planner, scenario, grid, i))
    return rows
