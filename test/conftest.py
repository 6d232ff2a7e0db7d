"""Test isolation: each run gets its own DDS domain, discovery stays on this host."""

import os
import random

# before rclpy is imported anywhere: 233 and up fail here with "port number is too high"
os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 232))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
