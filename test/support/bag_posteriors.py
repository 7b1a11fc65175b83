"""GPIS posteriors of the shipped bags (built once per test session, shared by the core tests)."""

from __future__ import annotations

import functools
from pathlib import Path

from gpis_grasp_ros.core.gpis import GpisPosterior

BAG_DIR = Path(__file__).resolve().parents[2] / 'bags'
BAGS = tuple(sorted(BAG_DIR.glob('*.mcap')))


@functools.lru_cache(maxsize=1)
def bag_posteriors() -> dict[str, GpisPosterior]:
    """``{bag stem: posterior}`` for every shipped bag (segmentation + GPIS as the nodes do)."""
    from gpis_grasp_ros.data.bags import load_bag, posterior_from_scene

    return {path.stem: posterior_from_scene(load_bag(path))[0] for path in BAGS}
