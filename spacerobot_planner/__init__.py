"""A Laplace-potential capture planner for a space robot, and its ROS 2 node (see the README)."""

from .cores import prefer_threading_layers
from .jit_cache import ensure_writable_cache

ensure_writable_cache()            # a read-only install: numba's cache where it can be written
prefer_threading_layers()          # numba's parallel loops on OpenMP, else TBB, before its work queue
