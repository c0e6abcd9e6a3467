"""Segmenters built into the core: the ``classical`` one (background subtraction, voxel hull,
tracking); learned ones come as plugins (``mosiv-sam2``)."""

from mosiv_framework.segment.classical import ClassicalOptions, ClassicalSegmenter

__all__ = ["ClassicalOptions", "ClassicalSegmenter"]
