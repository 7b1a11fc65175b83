"""Static rendering: the noise-free colour and depth images every frame is drawn from.

Colour is anti-aliased (SUBSAMPLES x SUBSAMPLES rays per pixel) with faint static textures, the cast
shadow darkening the table, transparent parts showing the tinted table behind them, dark parts dimmed
and specular parts a saturated metallic highlight. Depth is one pixel-centre ray per pixel (the sensor
measures one depth per pixel), with no return on specular surfaces and in projector shadows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from gpis_grasp_ros.sim.scene.raytrace import RayTracer
from gpis_grasp_ros.sim.scene.sensor import depth_edges
from gpis_grasp_ros.sim.scene.spec import L_DARK, L_NOISY, L_OPAQUE, L_SPECULAR, L_TRANSPARENT
from gpis_grasp_ros.sim.scene.view import ImageWindow

SUBSAMPLES = 3  # per pixel and axis, for anti-aliased colour
TRANSPARENT_TINT = 0.30


@dataclass
class StaticImage:
    """The noise-free images of a scene, (H, W) per pixel: ``colour`` (H, W, 3) float RGB, ``spec_frac``
    (fraction of the pixel on a specular surface), ``shadow_fraction`` (fraction showing the table in the
    light's cast shadow, 0 without a light); from the pixel-centre ray: ``rays`` (H, W, 2) slopes,
    ``label`` (material label, transparent where the table is seen through a transparent part),
    ``object`` (0 table, 1 target, 2 + j distractor j), ``shadow_px`` (projector shadow), ``clean_depth``
    (m, NaN = no return) and ``edge`` (near a depth edge)."""

    colour: np.ndarray
    spec_frac: np.ndarray
    shadow_fraction: np.ndarray
    rays: np.ndarray
    label: np.ndarray
    object: np.ndarray
    shadow_px: np.ndarray
    clean_depth: np.ndarray
    edge: np.ndarray


def smooth_field(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """Zero-mean, unit-std spatially correlated random field."""
    f = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_px, mode='reflect')
    return (f - f.mean()) / max(float(f.std()), 1e-12)


def render_static(rng: np.random.Generator, window: ImageWindow, tracer: RayTracer, table_color: np.ndarray,
                  shadow_strength: float) -> StaticImage:
    """Render the static images of the scene ``tracer`` sees through ``window``; the textures are the
    first draws from ``rng``, so every frame's randomness follows in a fixed order."""
    surfaces = tracer.surfaces
    s = SUBSAMPLES
    offsets = (np.arange(s) + 0.5) / s - 0.5
    shape = (window.height, window.width)
    # static textures (drawn first so every frame's randomness follows in a fixed order)
    table_tex = 1.0 + 0.025 * smooth_field(rng, shape, 6.0)
    object_tex = 1.0 + 0.03 * smooth_field(rng, shape, 2.0)
    glint = smooth_field(rng, shape, 1.5)
    metal = np.array([150.0, 152.0, 158.0]) * (1.0 + 0.12 * glint[..., None])
    highlight = np.clip((glint - 0.4) * 1.5, 0.0, 1.0)[..., None]  # ~1/3 of the surface, some saturated
    specular_rgb = metal + (255.0 - metal) * 1.5 * highlight

    colour = np.zeros(shape + (3,))
    spec_frac = np.zeros(shape)
    shadow_frac = np.zeros(shape)
    table = table_color * table_tex[..., None]
    for oy in offsets:
        for ox in offsets:
            rays = window.pixel_rays((ox, oy))
            hit, _, wall, passed = tracer.trace(rays)
            label = surfaces.kind_of_id[hit]
            # tint of the first transparent surface along the ray (top-face point approximation)
            tint_id = surfaces.lookup(tracer.top_points(rays))
            tint_id = np.where(surfaces.kind_of_id[tint_id] == L_TRANSPARENT, tint_id, 1)
            lit = table
            if surfaces.shadow is not None:  # cast shadow: darker, same chromaticity
                dark = surfaces.lookup(tracer.pose.table_points(rays), surfaces.shadow)
                lit = table * np.where(dark, 1.0 - float(shadow_strength), 1.0)[..., None]
                shadow_frac += dark & (label == 0)
            tinted = (1 - TRANSPARENT_TINT) * lit + TRANSPARENT_TINT * surfaces.color_of_id[tint_id]
            c = np.where(passed[..., None], tinted, lit)
            obj = surfaces.color_of_id[hit] * object_tex[..., None] * np.where(wall, 0.65, 1.0)[..., None]
            c = np.where(np.isin(label, (L_OPAQUE, L_NOISY))[..., None], obj, c)
            c = np.where((label == L_DARK)[..., None], 0.3 * obj, c)
            c = np.where((label == L_SPECULAR)[..., None], specular_rgb * np.where(wall, 0.65, 1.0)[..., None], c)
            colour += c
            spec_frac += label == L_SPECULAR

    # depth from the pixel-centre ray (the sensor measures one depth per pixel)
    rays = window.pixel_rays()
    hit, depth, _, passed = tracer.trace(rays)
    label = surfaces.kind_of_id[hit]
    shadow = tracer.projector_shadow(rays, label)
    clean = np.where((label == L_SPECULAR) | shadow, np.nan, depth)
    return StaticImage(colour=colour / (s * s), spec_frac=spec_frac / (s * s), shadow_fraction=shadow_frac / (s * s),
                       rays=rays, label=np.where((label == 0) & passed, L_TRANSPARENT, label).astype(np.uint8),
                       object=surfaces.obj_of_id[hit], shadow_px=shadow, clean_depth=clean, edge=depth_edges(clean))
