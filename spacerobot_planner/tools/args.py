"""What the ``spacerobot-plan`` commands share: a parser that exits 1 on bad input, postures, grids."""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from ..config import check_value, load_scenario

__all__ = ["ArgError", "Parser", "fail_input", "posture", "with_cells", "parse", "load"]


class ArgError(Exception):
    """A command line argparse refused (exit status 1, not argparse's 2)."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser that raises :class:`ArgError` instead of exiting."""

    def error(self, message):          # exit 1 (bad input), not argparse's 2 (= "no path")
        raise ArgError(message)


def with_cells(scenario, cells: list):
    """Return the scenario on a grid of ``cells`` (``--cells``: one value for all joints, or one per joint)."""
    dof = scenario.robot.dof
    full = list(cells) * dof if len(cells) == 1 else list(cells)
    try:
        check_value("grid.cells", full)
    except ValueError as e:           # the option the user typed, not the file's field
        raise ValueError(f"--cells: {str(e).removeprefix('grid.cells: ')}") from None
    if len(full) != dof:
        raise ValueError(f"--cells: expected 1 or {dof} values, got {len(cells)}")
    return scenario.with_grid(scenario.grid_with_cells(full))


def posture(robot, values, flag: str) -> np.ndarray:
    """Return a posture given in degrees on the command line as (dof,) rad; ValueError naming ``flag``."""
    if len(values) != robot.dof:
        raise ValueError(f"{flag}: expected {robot.dof} values "
                         f"({', '.join(robot.planned_names)}), got {len(values)}")
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{flag}: values must be finite numbers")
    return robot.validate_q(np.radians(values), flag)


def fail_input(message: str) -> int:
    """Print the bad-input message on stderr; return exit status 1."""
    print(f"spacerobot-plan: error: {message}", file=sys.stderr)
    return 1


def parse(ap: argparse.ArgumentParser, argv) -> tuple:
    """Return (args, None), or (None, exit status): 1 for a command line argparse refused, 0 after ``--help``."""
    try:
        return ap.parse_args(argv), None
    except ArgError as e:
        return None, fail_input(str(e))
    except SystemExit as e:            # --help
        return None, int(e.code or 0)


def load(params_file):
    """Return the scenario of a parameter file, its warnings on stderr (ValueError naming a bad field)."""
    return load_scenario(params_file, warn=lambda line: print(f"spacerobot-plan: warning: {line}", file=sys.stderr))
