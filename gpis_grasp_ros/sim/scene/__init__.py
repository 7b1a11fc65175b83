"""Simulated RGB-D camera (PrimeSense Carmine or RealSense D400) over planar objects on a table.

Produces the sensor streams of the paper's set-up (section III-B, Fig. 1): registered RGB and depth
from a head-mounted Carmine, 10 frames, transparent parts that show the table, specular parts with no
depth return, and Kinect-style noise, quantisation, drop-outs and projector shadows; a tilted camera,
a light casting shadows, distractor objects and a D400 sensor model go beyond it. Objects are right
prisms (a planar outline extruded ``height`` up from the table); rays are traced through them, so walls
facing the optical axis are seen at off-axis positions, exactly like a perspective camera. Ground truth
(occupancy, signed distance, centre of mass, outline) is for the simulated gripper and the evaluation,
never for the perception pipeline.

Modules, in the order a scene is built: :mod:`.polygons` and :mod:`.outlines` (outline geometry and
files), :mod:`.spec` (what a scene is: materials, distractors, camera, light, sensor), :mod:`.view`
(camera pose, frames, image window), :mod:`.surfaces` (object, regions and distractors as a surface
raster; cast shadows), :mod:`.raytrace`, :mod:`.render` (noise-free images), :mod:`.sensor` (per-frame
noise), :mod:`.simulator` (:class:`Scene`, ground truth) and :mod:`.bag` (messages, MCAP bags).
"""

from gpis_grasp_ros.sim.scene.bag import scene_messages, write_scene_bag
from gpis_grasp_ros.sim.scene.outlines import load_mask_png, load_polygon_csv, mask_to_polygon, save_polygon_csv
from gpis_grasp_ros.sim.scene.polygons import (
    points_in_polygon,
    polygon_area,
    polygon_centroid,
    polygon_signed_distance,
    rasterise_polygon,
    validate_polygon,
)
from gpis_grasp_ros.sim.scene.render import TRANSPARENT_TINT, StaticImage
from gpis_grasp_ros.sim.scene.sensor import Frame, disparity_quantise
from gpis_grasp_ros.sim.scene.simulator import GroundTruth, Scene
from gpis_grasp_ros.sim.scene.spec import (
    FRAME_ID,
    L_DARK,
    L_NOISY,
    L_OPAQUE,
    L_SPECULAR,
    L_TRANSPARENT,
    MATERIAL_KINDS,
    REALSENSE_D400_CAMERA,
    SENSORS,
    CameraModel,
    Distractor,
    MaterialRegion,
    SceneSpec,
)
from gpis_grasp_ros.sim.scene.surfaces import shadow_shift

__all__ = [
    'FRAME_ID', 'L_DARK', 'L_NOISY', 'L_OPAQUE', 'L_SPECULAR', 'L_TRANSPARENT', 'MATERIAL_KINDS',
    'REALSENSE_D400_CAMERA', 'SENSORS', 'TRANSPARENT_TINT', 'CameraModel', 'Distractor', 'Frame', 'GroundTruth',
    'MaterialRegion', 'Scene', 'SceneSpec', 'StaticImage', 'disparity_quantise', 'load_mask_png',
    'load_polygon_csv', 'mask_to_polygon', 'points_in_polygon', 'polygon_area', 'polygon_centroid',
    'polygon_signed_distance', 'rasterise_polygon', 'save_polygon_csv', 'scene_messages', 'shadow_shift',
    'validate_polygon', 'write_scene_bag',
]
