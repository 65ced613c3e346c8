"""Fixtures of the simulator's tests: each block is generated once per session."""

from __future__ import annotations

import pytest
from synthetic_blocks import LAYOUT, SMALL

from simulator.simulate import simulate_orchard


@pytest.fixture(scope="session")
def small():
    return simulate_orchard(SMALL)


@pytest.fixture(scope="session")
def gappy():
    return simulate_orchard(LAYOUT)
