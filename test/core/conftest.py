"""Fixtures of the core tests."""

from __future__ import annotations

import numpy as np
import pytest
from image_pairs import texture


@pytest.fixture(scope="session")
def textures() -> dict[str, np.ndarray]:
    return {name: texture(name) for name in ("astronaut", "coffee", "chelsea", "brick")}
