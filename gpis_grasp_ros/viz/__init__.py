"""Images of grids, GPIS and grasps (numpy + OpenCV). May import ``core`` and ``viz``."""
