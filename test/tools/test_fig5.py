"""Fig. 5 study: the plane's frame, part labels and the uncertainty patterns of the scene generator."""

from __future__ import annotations

import numpy as np
import pytest

from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.sensing import SensingParams
from gpis_grasp_ros.data.bags import load_bag
from gpis_grasp_ros.sim.objects import toy_plane
from gpis_grasp_ros.tools.benchmark import fig5
from gpis_grasp_ros.tools.evaluation.tasks import segment_scene


def test_plane_frame_matches_the_catalogue_object() -> None:
    """The wing region of sim.objects.toy_plane() is WING_CM placed by plane_to_scene (catches a changed plane)."""
    spec = toy_plane()
    assert np.allclose(spec.regions[0].polygon, fig5.plane_to_scene(fig5.WING_CM), atol=1e-12)
    pts = np.random.default_rng(0).uniform(-8, 8, (50, 2))
    assert np.allclose(fig5.scene_to_plane(fig5.plane_to_scene(pts)), pts, atol=1e-12)


@pytest.mark.parametrize('point, part', [((6.5, 0.0), 'nose'), ((-7.8, 0.1), 'tail'), ((-6.5, -2.5), 'stabiliser'),
                                         ((1.5, 3.0), 'wing'), ((1.5, -6.8), 'wing tip'), ((-3.0, 0.9), 'fuselage')])
def test_parts(point: tuple[float, float], part: str) -> None:
    assert fig5.part_of(np.array(point)) == part


def test_agreement_rules() -> None:
    assert fig5.agrees(('nose', 'tail'), (frozenset({'nose', 'tail'}),))
    assert not fig5.agrees(('fuselage', 'fuselage'), (frozenset({'nose', 'tail'}),))
    assert fig5.agrees(('wing tip', 'wing tip'), (frozenset({'wing tip'}),))
    assert not fig5.agrees(('wing', 'wing tip'), (frozenset({'wing tip'}),))
    with pytest.raises(ValueError):
        fig5.pattern_regions('tail_only')


def test_unobserved_nose_is_uncertain_and_the_tail_is_not(tmp_path) -> None:
    """The 'nose' pattern's bag gives a GPIS whose σ near the nose tip exceeds σ near the tail end."""
    bag = fig5.write_pattern_bags(tmp_path, ['nose'])[0]
    # as the benchmark segments (D is wider than the gripper)
    sensing, _ = segment_scene(load_bag(bag), SensingParams(grid_size=25), relax_opening=True)
    posterior = posterior_from_grids(*publishable_grids(sensing))
    g = posterior.geometry
    sd = np.sqrt(posterior.variance)

    def sd_at(point_cm: tuple[float, float]) -> float:
        xy = fig5.plane_to_scene(np.array([point_cm]))[0]
        col, row = np.floor((xy - [g.origin_x, g.origin_y]) / g.resolution).astype(int)
        return float(sd[row, col])

    assert sd_at((6.6, 0.0)) > 3 * sd_at((-7.9, 0.0))


def test_contacts_on_unobserved_regions() -> None:
    pts_cm = np.array([[6.8, 0.0], [-7.9, 0.0], [1.6, -3.5], [2.9, -3.5], [1.6, -7.0]])
    pts = fig5.plane_to_scene(pts_cm)
    assert list(fig5.on_uncertain(pts, fig5.pattern_regions('nose'))) == [True, False, False, False, False]
    assert list(fig5.on_uncertain(pts, fig5.pattern_regions('front_back'))) == [True, True, False, False, False]
    # Edge pattern: the inner wing is observed, its leading edge and tip are not.
    assert list(fig5.on_uncertain(pts, fig5.pattern_regions('wing_edges'))) == [False, False, False, True, True]
    assert list(fig5.on_uncertain(pts, fig5.pattern_regions('wings'))) == [False, False, True, True, True]
