"""
``spacerobot-plan envelope``: capture envelope maps, the capture planned at every target pose of a grid.

    spacerobot-plan envelope --params-file F --x-m X0 X1 NX --y-m Y0 Y1 NY
        [--yaw-deg A0 A1 NA] [--starts-deg A B ... [--starts-deg ...]] --out DIR
        [--scheduler tcp://host:8786 | --workers N] [--cells N] [--chunk-size N]
        [--parquet {auto,yes,no}] [--no-plots] [--quiet]

Each range is inclusive with a count (``--x-m -4 -2 5``: five values from −4 to −2 m): the
target body's centre and yaw.  Every pose is planned as ``spacerobot-plan`` plans one
request (``offline.plan_offline``), its goal the grasp of that pose's target (a
``scenario.goal_deg`` does not apply), from the scenario's start or from each
``--starts-deg`` posture (the flag once per posture).  Rows stream to ``DIR/envelope.csv`` as
chunks finish; a rerun into the same folder plans only the poses not yet there.  The maps
(PNG, one per yaw and start) go to ``DIR`` when every pose is done.

Runs on a Dask ``LocalCluster`` on this machine (one process per core) by default, on a
running Dask cluster with ``--scheduler``, or in this process with ``--workers 0``.

Exit status: 0 every pose has its row (whatever its code), 1 bad input (the message names
the field), 3 the sweep stopped before every pose was done (rerun to resume).
"""

from __future__ import annotations

import argparse
import collections
import math
import sys
from pathlib import Path

from ..config import check_value
from ..envelope.engine import run_envelope
from ..envelope.store import sweep_spec
from ..envelope.sweep import PoseGrid, axis_values
from .args import Parser, fail_input, load, parse, posture, with_cells

__all__ = ["main", "build_parser"]


def build_parser() -> argparse.ArgumentParser:
    ap = Parser(prog="spacerobot-plan envelope", description=__doc__.strip().split("\n\n")[0].replace("``", ""),
                formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params-file", required=True, help="ROS 2 parameter file (any scenario, any acs.mode)")
    ap.add_argument("--x-m", type=float, nargs=3, required=True, metavar=("X0", "X1", "NX"),
                    help="target centre x: from X0 to X1 m inclusive, NX values")
    ap.add_argument("--y-m", type=float, nargs=3, required=True, metavar=("Y0", "Y1", "NY"),
                    help="target centre y: from Y0 to Y1 m inclusive, NY values")
    ap.add_argument("--yaw-deg", type=float, nargs=3, metavar=("A0", "A1", "NA"),
                    help="target yaw: from A0 to A1 deg inclusive, NA values (default: the scenario's yaw)")
    ap.add_argument("--starts-deg", type=float, nargs="+", action="append", metavar="DEG",
                    help="a start posture of the planned joints, degrees; once per posture "
                         "(default: scenario.start_deg)")
    ap.add_argument("--out", required=True, metavar="DIR", help="the sweep's folder (envelope.csv, maps)")
    ap.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://host:8786)")
    ap.add_argument("--workers", type=int, metavar="N",
                    help="local worker processes (default: one per core); 0: in this process, without Dask")
    ap.add_argument("--cells", type=int, nargs="+", metavar="N",
                    help="grid cells per planned joint (one value for all, or one per joint)")
    ap.add_argument("--chunk-size", type=int, metavar="N",
                    help="poses per task (default: large chunks first, small ones last, whole target poses)")
    ap.add_argument("--parquet", choices=("auto", "yes", "no"), default="auto",
                    help="also write envelope.parquet (auto: for 10,000 poses or more)")
    ap.add_argument("--no-plots", action="store_true", help="no PNG maps")
    ap.add_argument("--quiet", action="store_true", help="no progress bar, no summary")
    return ap


#: the most poses one sweep plans (its rows and pose ids are held in memory)
MAX_POSES = 50_000_000


def _count(value: float, flag: str) -> int:
    if not math.isfinite(value) or value != int(value):
        raise ValueError(f"{flag}: the count must be an integer, got {value}")
    if value > MAX_POSES:
        raise ValueError(f"{flag}: {value:.0f} values, more than one sweep holds ({MAX_POSES} poses); split it "
                         "into several sweeps")
    return int(value)


def _scheduler(address: str | None) -> str | None:
    """Return ``--scheduler``'s address as Dask takes it; ValueError naming the flag for one it would not."""
    if address is None:
        return None
    address = address.strip()
    if not address:
        raise ValueError("--scheduler: an empty address (give tcp://HOST:PORT, or leave the flag out for a local "
                         "cluster)")
    scheme, sep, rest = address.rpartition("://")
    host, colon, port = (rest if sep else address).rpartition(":")
    if (sep and scheme not in ("tcp", "tls", "inproc", "ucx", "ws", "wss")) or not colon or not host \
            or not port.isdigit():
        raise ValueError(f"--scheduler: {address!r} is not a Dask scheduler's address (tcp://HOST:PORT, as "
                         "`dask scheduler` prints it)")
    return address


def main(argv=None) -> int:
    args, rc = parse(build_parser(), argv)
    if args is None:
        return rc
    try:
        scenario = load(args.params_file)
        if args.cells is not None:
            scenario = with_cells(scenario, args.cells)
        if scenario.scene.target is None:
            raise ValueError("target: the scenario has no target; an envelope sweeps the target's pose")
        scheduler = _scheduler(args.scheduler)
        if scheduler is not None and args.workers is not None:
            raise ValueError("--workers: the cluster at --scheduler has its own workers; give one of the two")
        counts = [_count(args.x_m[2], "--x-m"), _count(args.y_m[2], "--y-m")]
        if args.yaw_deg is not None:
            counts.append(_count(args.yaw_deg[2], "--yaw-deg"))
        if math.prod(counts) * max(1, len(args.starts_deg or ())) > MAX_POSES:      # before any axis is built
            raise ValueError(f"--x-m/--y-m/--yaw-deg/--starts-deg: {math.prod(counts)} poses a start, more than "
                             f"one sweep holds ({MAX_POSES}); split it into several sweeps")
        for flag, ends, k in (("--x-m", args.x_m, 0), ("--y-m", args.y_m, 1)):    # the file's target.center_m range
            for end in ends[:2]:
                try:
                    check_value("target.center_m", [end if j == k else 0.0 for j in range(2)])
                except ValueError as e:
                    raise ValueError(f"{flag}: {e} (the range of the file's target.center_m)") from None
        xs = axis_values(args.x_m[0], args.x_m[1], counts[0], "--x-m")
        ys = axis_values(args.y_m[0], args.y_m[1], counts[1], "--y-m")
        if args.yaw_deg is None:
            yaws = (math.degrees(scenario.scene.target.yaw_rad),)
        else:
            yaws = axis_values(args.yaw_deg[0], args.yaw_deg[1], counts[2], "--yaw-deg")
            for end in args.yaw_deg[:2]:          # the range of the file's target.yaw_deg (was not checked: 400° ran)
                try:
                    check_value("target.yaw_deg", end)
                except ValueError as e:
                    raise ValueError(f"--yaw-deg: {e} (the range of the file's target.yaw_deg)") from None
        if args.starts_deg:
            starts = [posture(scenario.robot, s, "--starts-deg") for s in args.starts_deg]
        elif scenario.start_rad is not None:
            starts = [scenario.start_rad]
        else:
            raise ValueError("--starts-deg: no start given and the file has no scenario.start_deg")
        grid = PoseGrid(xs, ys, yaws, tuple(tuple(s) for s in starts))
        if grid.n_poses > MAX_POSES:
            raise ValueError(f"--x-m/--y-m/--yaw-deg/--starts-deg: {grid.n_poses} poses, more than one sweep "
                             f"holds ({MAX_POSES}); split it into several sweeps")
        spec = sweep_spec(args.params_file, scenario.grid.cells, grid)
        parquet = {"auto": None, "yes": True, "no": False}[args.parquet]
        if not args.quiet:
            print(f"envelope {args.params_file}: {grid.n_poses} poses ({len(xs)} x × {len(ys)} y × {len(yaws)} "
                  f"yaw × {len(starts)} start), grid {scenario.grid.label()}, into {args.out}", flush=True)
        report = run_envelope(scenario, grid, args.out, spec, scheduler=scheduler, workers=args.workers,
                              chunk_size=args.chunk_size, parquet=parquet, quiet=args.quiet)
    except ValueError as e:
        return fail_input(str(e))
    except OSError as e:
        return fail_input(f"--out {args.out}: {e}")
    except KeyboardInterrupt:
        print("spacerobot-plan envelope: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    if not args.quiet:
        rate = report.planned / report.plan_seconds if report.plan_seconds > 0 else float("nan")
        print(f"planned {report.planned} poses this run ({report.done_before} done before) in "
              f"{report.seconds:.1f} s on {report.engine}, {report.chunks} chunks; {rate:.1f} poses/s "
              "while planning")
    if not report.complete:
        print(f"spacerobot-plan envelope: {report.n_poses - report.done_before - report.planned} poses not "
              f"planned; run the same command again to resume", file=sys.stderr)
        return 3
    if not args.quiet:
        codes = collections.Counter(r["code"] for r in report.rows)
        print("codes: " + ", ".join(f"{c} {n}" for c, n in codes.most_common()))
        for name in ("envelope.csv", "envelope.parquet"):
            if (Path(args.out) / name).exists():
                print(f"wrote {Path(args.out) / name}")
    if not args.no_plots:
        from ..envelope.plots import plot_envelope     # matplotlib: loaded only when maps are drawn
        try:
            written = plot_envelope(report.rows, scenario, grid, args.out)
        except OSError as e:
            return fail_input(f"--out {args.out}: the maps: {e} (the table is written; rerun with the same command "
                              "to draw them)")
        except KeyboardInterrupt:
            print("spacerobot-plan envelope: interrupted while drawing the maps (the table is written; rerun with "
                  "the same command to draw them)", file=sys.stderr)
            return 130
        for path in written:
            if not args.quiet:
                print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
