"""Session-wide isolation for every test: a DDS domain of our own, discovery on this host only.

pytest.ini runs the tests in parallel workers (pytest-xdist); each worker is its own session and needs its own
domain, or two graphs with the same topic names would cross-talk. The workers of one run share a random base (from
the run's id) and add their worker index, so they never collide with each other and rarely with a parallel run."""
import os
import random
import zlib

# Pick the domain before any test imports rclpy; child processes inherit it.
if 'MM_TEST_KEEP_DOMAIN' not in os.environ:
    run_id = os.environ.get('PYTEST_XDIST_TESTRUNUID')
    base = zlib.crc32(run_id.encode()) if run_id else random.SystemRandom().randrange(101)
    worker = int(os.environ.get('PYTEST_XDIST_WORKER', 'gw0')[2:] or 0)
    os.environ['ROS_DOMAIN_ID'] = str(1 + (base + worker) % 101)
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
