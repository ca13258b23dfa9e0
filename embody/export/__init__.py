"""Trajectory file formats that robot learning stacks consume (see `formats`)."""

from embody.export.formats import FORMATS, ExportFormat, read_trajectory, write_trajectory

__all__ = ["FORMATS", "ExportFormat", "read_trajectory", "write_trajectory"]
