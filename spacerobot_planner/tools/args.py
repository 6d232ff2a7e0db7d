"""What the ``spacerobot-plan`` commands share: a parser that exits 1 on bad input, postures, grids."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

from ..config import check_value, load_scenario

__all__ = ["ArgError", "Parser", "fail_input", "posture", "with_cells", "parse", "load", "output_file",
           "folder_to_write", "option_value"]


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


def option_value(name: str, value, flag: str):
    """Return ``config.check_value(name, value)``; its ValueError names ``flag``, the option typed, not the field."""
    try:
        return check_value(name, value)
    except ValueError as e:
        raise ValueError(f"{flag}: {str(e).removeprefix(name + ': ')}") from None


def output_file(path: str, flag: str, formats=None, default_suffix: str = "") -> Path:
    """
    Return the file ``flag`` names for output, checked before any work (ValueError naming ``flag``).

    Not a folder; its folder one that exists or can be made (the nearest that exists a folder this
    process may write in).  ``formats``: the suffixes allowed (without the dot, lower case); a name
    without a suffix gets ``default_suffix`` (the file then written is the one returned).
    """
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{flag}: {path} is a folder; give a file name (e.g. {p / ('plan' + default_suffix)})")
    if formats is not None:
        if not p.suffix and default_suffix:
            p = p.with_name(p.name + default_suffix)
        if p.suffix.lower().lstrip(".") not in formats:
            raise ValueError(f"{flag}: {path}: '{p.suffix}' is not a format it writes; one of "
                             f"{', '.join('.' + f for f in sorted(formats))}")
    folder_to_write(p.parent, flag, path)
    return p


def folder_to_write(folder, flag: str, given=None) -> None:
    """
    Check that ``folder`` exists or can be made, for writing (ValueError naming ``flag`` and ``given``).

    The nearest of it and the folders above it that exists must be a folder this process may write in.
    """
    given = folder if given is None else given
    above = Path(folder)
    while not above.exists() and above != above.parent:
        above = above.parent
    if not above.is_dir():
        raise ValueError(f"{flag}: {given}: {above} is a file, not a folder")
    if not os.access(above, os.W_OK | os.X_OK):
        raise ValueError(f"{flag}: {given}: cannot write in {above} (permission denied)")


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
