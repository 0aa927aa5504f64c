"""Session-wide isolation for every test: a DDS domain of our own, discovery on this host only."""
import os
import random

# Pick the domain before any test imports rclpy; child processes inherit it, so parallel runs never cross-talk.
if 'MM_TEST_KEEP_DOMAIN' not in os.environ:
    os.environ['ROS_DOMAIN_ID'] = str(random.SystemRandom().randint(1, 101))
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
