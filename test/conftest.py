"""Test isolation and hypothesis profiles.

Each run gets its own DDS domain and discovery stays on this host.  Property tests
run a few dozen cases by default; ``pytest --hypothesis-profile=long`` (or
``make test-long``) runs thousands.
"""

import os
import random

from hypothesis import HealthCheck, settings

# before rclpy is imported anywhere: 233 and up fail here with "port number is too high"
os.environ["ROS_DOMAIN_ID"] = str(random.SystemRandom().randint(1, 232))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

_common = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=False)
settings.register_profile("default", max_examples=30, **_common)
settings.register_profile("ci", max_examples=30, derandomize=True, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("long", max_examples=3000, **_common)
settings.load_profile("ci" if os.environ.get("CI") else "default")
