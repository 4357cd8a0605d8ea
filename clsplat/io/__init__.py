"""File I/O: images and depth maps (OpenImageIO), Gaussian .ply files, contact sheets."""
from .images import read_depth, read_image, write_depth, write_image
from .ply import read_ply, write_ply, GaussianPly
from .contact_sheet import make_contact_sheet

__all__ = ["read_image", "write_image", "read_depth", "write_depth", "read_ply", "write_ply", "GaussianPly",
           "make_contact_sheet"]
