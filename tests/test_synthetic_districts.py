"""The generator's districts (issue 25, deliverable 3): their own block types."""

from __future__ import annotations

import numpy as np
import pytest

from obliq_colmap.synthetic import build_city
from obliq_colmap.synthetic.options import (
    DISTRICT_BLOCKS,
    PRESETS,
    SCENE_CLASSES,
    SceneOptions,
    preset,
)


def _city(district: str, seed: int = 3):
    return build_city(preset("small", district=district), seed)


def test_every_district_sums_to_one_and_names_a_block_type():
    for kinds in DISTRICT_BLOCKS.values():
        assert sum(kinds.values()) == pytest.approx(1.0)
    assert set(SCENE_CLASSES) <= set(PRESETS)


def test_unknown_district_lists_the_allowed():
    with pytest.raises(ValueError, match="industrial"):
        SceneOptions(district="suburb")


@pytest.mark.slow
def test_industrial_district_has_halls():
    city = _city("industrial")
    halls = [b for b in city.buildings if b.style[0] > b.height_m]  # one storey
    assert len(halls) >= 3
    heights = np.array([b.height_m for b in halls])
    assert heights.min() >= 6.0 and heights.max() <= 12.0
    areas = np.array([b.footprint.area for b in halls])
    assert np.median(areas) > 600.0  # halls, not houses


@pytest.mark.slow
def test_highrise_district_has_towers():
    city = _city("highrise")
    heights = np.array([b.height_m for b in city.buildings])
    assert (heights >= 40.0).sum() >= 2


@pytest.mark.slow
def test_houses_district_is_mostly_pitched_roofs():
    city = _city("houses")
    pitched = np.mean([b.roof in ("gabled", "hipped") for b in city.buildings])
    assert pitched > 0.6
    assert max(b.height_m for b in city.buildings) < 10.0
