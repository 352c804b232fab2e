"""Old home of the COLMAP and NeuS/IDR readers and of lenses, kept for the imports that still name
it: the code is in vq_mitsuba.data.formats.colmap, vq_mitsuba.data.formats.idr and
vq_mitsuba.data.lens."""

from vq_mitsuba.data.cameras import camera_from_intrinsics
from vq_mitsuba.data.formats.colmap import colmap_model_dir, read_colmap, read_colmap_points, write_colmap
from vq_mitsuba.data.formats.idr import read_idr_sphere, write_idr
from vq_mitsuba.data.lens import Lens, distort_image, undistort_image

__all__ = ["camera_from_intrinsics", "colmap_model_dir", "read_colmap", "read_colmap_points", "write_colmap",
           "read_idr_sphere", "write_idr", "Lens", "distort_image", "undistort_image"]
