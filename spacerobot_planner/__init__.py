"""A Laplace-potential capture planner for a space robot, and its ROS 2 node (see the README)."""

from .cores import prefer_threading_layers

prefer_threading_layers()          # numba's parallel loops on OpenMP, else TBB, before its work queue
