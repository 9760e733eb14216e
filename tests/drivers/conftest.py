"""Fixtures of the arm tests: ``arm``, the ``rig`` fixture's arm (each module's ``rig``: the arms
it runs against, with their simulators) brought home and its log marked before each test."""
from __future__ import annotations

import pytest


@pytest.fixture
def arm(rig):
    rig.reset()
    return rig.arm
