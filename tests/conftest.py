"""Fixtures for the multi-process graph and replay tests."""
import pytest
from mm_common.ros_harness import RosHarness


@pytest.fixture
def ros():
    harness = RosHarness()
    yield harness
    harness.close()
