"""Old home of the nerfstudio transforms.json reader and writer, kept for the imports that still
name it: the code is in vq_mitsuba.data.formats.nerfstudio."""

from vq_mitsuba.data.formats.nerfstudio import write_transforms_json

__all__ = ["write_transforms_json"]
