"""The synthetic scenes' copies in the photographed formats are written by
vq_mitsuba.data.formats.copies (each format's own writer in its module); kept for the imports
that still name this module."""

from vq_mitsuba.data.formats.copies import format_frames, write_photo_formats

__all__ = ["format_frames", "write_photo_formats"]
