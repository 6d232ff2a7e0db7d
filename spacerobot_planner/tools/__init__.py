"""
Tools around the planning core.

The offline CLI (``spacerobot-plan``), the closed-loop demo, the plots, and the helper that lays out
the ROS 2 install tree of a virtualenv.
"""
