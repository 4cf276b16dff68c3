import math

import pytest

from ragsplat.water_surface import WaterSurface


def test_defaults():
    water = WaterSurface()
    assert (water.level, water.n) == (0.0, 1.33)


@pytest.mark.parametrize("n", [0.99, float("nan"), float("inf"), -1.33])
def test_bad_index_raises(n):
    with pytest.raises(ValueError, match="refractive index"):
        WaterSurface(n=n)


def test_bad_level_raises():
    with pytest.raises(ValueError, match="level"):
        WaterSurface(level=math.inf)


def test_frozen():
    with pytest.raises(AttributeError):
        WaterSurface().n = 1.0
