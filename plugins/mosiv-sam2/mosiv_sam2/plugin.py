"""Entry point of the ``mosiv-sam2`` plugin: registers the ``sam2`` segmenter."""

from __future__ import annotations

from mosiv_framework.registry import Component, hookimpl


@hookimpl
def mosiv_segmenters(register):
    from mosiv_sam2.segmenter import Sam2Options, Sam2Segmenter

    register(
        Component(
            "segmenter",
            "sam2",
            factory=Sam2Segmenter,
            options=Sam2Options,
            description="SAM2 video masks, prompted per object by the classical hull's ids",
        )
    )
