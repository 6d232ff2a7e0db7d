"""
Capture envelope maps: the capture planned at every pose of a grid of target poses, on Dask.

- ``sweep.py``: the pose grid, its chunks, one chunk planned into rows (the single-plan
  pipeline, ``offline.plan_offline``, per pose);
- ``store.py``: the sweep's folder (streaming CSV, manifest, resume, Parquet);
- ``engine.py``: the chunks on a Dask cluster (local by default) or in this process, with a
  progress bar;
- ``plots.py``: the maps (feasibility and each metric over x–y, one figure per yaw and start).

``spacerobot-plan envelope`` (``tools/envelope_cli.py``) is the command; docs/envelope.md
the guide.  No rclpy here.
"""

from .engine import SweepReport, run_envelope
from .store import EnvelopeStore, read_rows, sweep_spec
from .sweep import COLUMNS, TIMING_COLUMNS, PoseGrid, axis_values, plan_chunk

__all__ = ["run_envelope", "SweepReport", "EnvelopeStore", "read_rows", "sweep_spec", "COLUMNS",
           "TIMING_COLUMNS", "PoseGrid", "axis_values", "plan_chunk"]
