"""Old home of the photographed captures' views, kept for the imports that still name it: each
format's views are in its module (vq_mitsuba.data.formats), the photos are read by
vq_mitsuba.data.formats.common.read_views and undistorted by vq_mitsuba.data.lens."""

from vq_mitsuba.data.formats.common import read_views
from vq_mitsuba.data.lens import undistort_photo as _undistorted

__all__ = ["read_views", "_undistorted"]
