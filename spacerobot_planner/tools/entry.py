"""
The executables' entry points (``setup.py``'s console scripts): numba imported the package's way first.

This module imports nothing heavy: each entry imports numba without its coverage support's import of
``coverage`` (``jit_cache.import_numba``: 25 ms of ``spacerobot-plan``'s start where ``make`` installed
it) before the module it runs imports numba.
"""

from __future__ import annotations

from ..jit_cache import import_numba

__all__ = ["plan", "planner_node", "mock_arm_node"]


def plan(argv=None) -> int:
    """
    ``spacerobot-plan``: ``tools.cli.run``.

    A Ctrl-C that the command does not take itself (while numba and the package load, during a
    plan) ends it with status 130 and one line, not a traceback.
    """
    try:
        import_numba()
        from .cli import run
        return run(argv)
    except KeyboardInterrupt:
        import sys
        print("spacerobot-plan: interrupted", file=sys.stderr)
        return 130


def planner_node(args=None) -> int:
    """``planner_node``: ``ros.planner_node.main``."""
    import_numba()
    from ..ros.planner_node import main
    return main(args)


def mock_arm_node(args=None) -> int:
    """``mock_arm_node``: ``ros.mock_arm_node.main``."""
    import_numba()
    from ..ros.mock_arm_node import main
    return main(args)
