"""Unseen stays uncertain: where the sensor failed the GPIS posterior sigma covers the true SDF, where it measured
an opaque surface the posterior stays confident (simulated scenes, segmentation and GPIS as the nodes run them)."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from gpis_grasp_ros.core.pipeline import posterior_from_grids, publishable_grids
from gpis_grasp_ros.core.sensing import CameraIntrinsics, SensingParams, segment_frames
from gpis_grasp_ros.sim.objects import crystal_knob
from gpis_grasp_ros.sim.scene import MaterialRegion, Scene, SceneSpec
from gpis_grasp_ros.tools.evaluation.truth import TrueShape


@functools.lru_cache(maxsize=4)
def _posterior(name: str, train_clear_body_height: bool = True):
    """(z, sigma m, failed cells, measured cells) of a generated scene on its planning grid."""
    if name == 'clear knob':  # a transparent body with no depth on it: its footprint is a prism (a prior)
        spec = dataclasses.replace(crystal_knob(), frames=4)
    else:  # an opaque 8 x 5 x 2.5 cm box, every part of it measured
        box = np.array([[-0.04, -0.025], [0.04, -0.025], [0.04, 0.025], [-0.04, 0.025]])
        spec = SceneSpec(outline=box, regions=[MaterialRegion('opaque', box * 1.1)], height=0.025, frames=4, seed=3)
    scene = Scene(spec)
    frames = list(scene.frames())
    fx, fy, cx, cy, w, h = scene.intrinsics
    result = segment_frames(np.stack([f.rgb for f in frames]), np.stack([f.depth for f in frames]),
                            CameraIntrinsics(fx, fy, cx, cy, w, h), SensingParams())
    occ, noise, geometry = publishable_grids(result)
    post = posterior_from_grids(occ, noise, geometry)
    gt = scene.ground_truth()
    truth = TrueShape(gt.sdf, gt.geometry, geometry).values_at(geometry.cell_centers())
    sigma = np.sqrt(post.variance)
    clear = result.clear_body | result.seen_behind
    failed = result.uncertain | clear
    measured = result.observed & result.train_mask & ~failed & ~result.occluded
    return np.abs(post.mean - truth) / sigma, sigma, failed, measured, truth


def test_clear_body_cells_keep_a_sigma_that_covers_their_true_sdf():
    z, sigma, failed, measured, _ = _posterior('clear knob')
    assert failed.sum() > 100  # the knob's prism and the table seen through it
    # calibrated: Gaussian errors give 1.64 at the 90th percentile; the prism's height prior entered as one shared
    # error keeps it below 2 (as a per-cell variance it was 2.6)
    assert np.percentile(z[failed], 90) <= 2.0


def test_a_fully_measured_opaque_object_stays_confident():
    z, sigma, failed, measured, truth = _posterior('opaque box')
    near = measured & (np.abs(truth) < 0.015)  # the box and the table around its edges
    assert near.sum() > 100
    assert failed.sum() <= 0.05 * near.sum()
    # every part seen in depth: a posterior sigma of a millimetre or less there (a grid cell is ~4 mm)
    assert np.percentile(sigma[near], 90) < 1.5e-3


@pytest.mark.parametrize('name', ['clear knob'])
def test_the_failed_cells_are_not_uncertain_without_cause(name):
    # over-confidence is caught above; under-confidence: most failed cells' errors are not far inside their sigma
    z, _, failed, _, _ = _posterior(name)
    assert np.median(z[failed]) > 0.2
