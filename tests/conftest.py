"""Shared fixtures: the reference cell and a small procedural part, built once per session."""
import numpy as np
import pytest

from simulator.cell import load_cell
from simulator.parts import block_with_holes_and_steps, part_from_mesh


@pytest.fixture(scope="session")
def cell():
    return load_cell()


@pytest.fixture(scope="session")
def block_part():
    return part_from_mesh(block_with_holes_and_steps(), name="block")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
