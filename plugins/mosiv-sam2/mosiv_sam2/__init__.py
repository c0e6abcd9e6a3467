"""SAM2 video segmentation for MOSIV, prompted and identified by the classical visual hull."""

from mosiv_sam2.segmenter import Sam2Options, Sam2Segmenter

__all__ = ["Sam2Options", "Sam2Segmenter"]
