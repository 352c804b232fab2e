"""The older name of `vq_mitsuba.engine.fit`, where `vq-mitsuba fit` runs."""

from vq_mitsuba.engine.fit import GEOMETRY_MODES, fit_capture, needs_reconstruction

__all__ = ["GEOMETRY_MODES", "fit_capture", "needs_reconstruction"]
