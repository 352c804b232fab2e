"""Captures: image I/O, cameras and datasets (Mitsuba XML or NeRF-synthetic json)."""
