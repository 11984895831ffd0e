"""Fixtures for the simulate tests."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(20240611)


@pytest.fixture(params=["cone", "parallel"])
def kind(request):
    return request.param
