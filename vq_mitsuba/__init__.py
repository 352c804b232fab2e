"""vq-mitsuba: neural reflectance decomposition and material editing (VQ-NeRF) on Mitsuba 3."""

__version__ = "0.1.0"
