"""Diagonal markers: detection, sub-pixel refinement and identification (point ids)."""

from .detect import detect
from .identify import identify
from .refine import refine
from .extract import predicted_projections, process_image

__all__ = ["detect", "identify", "predicted_projections", "process_image", "refine"]
