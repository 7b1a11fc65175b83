"""From RGBD frames of a tabletop to a target's occupancy grid and SDF noise map (paper section III-B).

:func:`segment_frames` runs, for a camera looking down at a table at any tilt (0-60 degrees; the paper's
PR2 head camera), these stages, one module each:

1. :mod:`.camera` - depth averaged per pixel over the frames with a valid return, colour over all frames;
   the independent frames the average is worth measured from their differences.
2. :mod:`.table` - the table plane (robust fit of the whole cloud, or given), heights along its normal; for a
   target point, :mod:`.window` - the part of the frame its grid depends on, where the stages below run.
3. :mod:`.evidence` - soft depth evidence (height above the plane) and a shadow-proof colour test, combined
   per pixel by inverse variance.
4. :mod:`.occlusion` - what was not measured: returns seen through a clear part, the sensor's shadow, and
   where a pixel without a return lies on its ray (the visual hull of the objects next to it).
5. :mod:`.objects` - evidence components in the table plane, split where objects touch (at necks, flat supports
   and height steps, :mod:`.steps`); the target.
6. :mod:`.clear_body` - the table seen through a clear target joins it; a clear body is a prism.
7. :mod:`.rasterise` - the square grid in the table plane around the target, cells from the pixels' feet.
8. :mod:`.noise_map` - the variance of each cell's SDF value and the cells the GPIS is not trained on.

The paper's rule holds throughout: a pixel without a valid return is **missing and counts as object** (o = 1)
unless it is shown to be table (the sensor's shadow, a hole off the object's visual hull). What was not seen
stays uncertain rather than free: missing cells, extended regions where depth and colour disagree and cells of
foreign no-return pixels are not GPIS training points and count as object in the SDF, so the GP's prior
governs them. The design of each stage is in docs/segmentation-stages.md.

Grid (x, y) are table-frame metres (:class:`~gpis_grasp_ros.core.grid.GridGeometry`; for a top-down camera
the camera's x, y at the table depth).
"""

from gpis_grasp_ros.core.sensing.camera import CameraIntrinsics, frames_from_clouds
from gpis_grasp_ros.core.sensing.chroma import chromaticity_distance
from gpis_grasp_ros.core.sensing.clear_body import clear_body_height, prism_footprint, seen_through
from gpis_grasp_ros.core.sensing.evidence import ColourModel, chromatic_extension, shadow_line_distance
from gpis_grasp_ros.core.sensing.morphology import nearest_pixel
from gpis_grasp_ros.core.sensing.objects import minimum_width, object_height, split_flat_support, split_touching
from gpis_grasp_ros.core.sensing.occlusion import column_zbuffer, occlusion_shadow_pixels, see_through_pixels
from gpis_grasp_ros.core.sensing.params import TARGET_MODES, SensingParams, SensingResult
from gpis_grasp_ros.core.sensing.segment import segment_frames

__all__ = [
    'TARGET_MODES', 'CameraIntrinsics', 'ColourModel', 'SensingParams', 'SensingResult', 'chromatic_extension',
    'chromaticity_distance', 'clear_body_height', 'column_zbuffer', 'frames_from_clouds', 'minimum_width',
    'nearest_pixel', 'object_height', 'occlusion_shadow_pixels', 'prism_footprint', 'see_through_pixels',
    'seen_through', 'segment_frames', 'shadow_line_distance', 'split_flat_support', 'split_touching',
]
