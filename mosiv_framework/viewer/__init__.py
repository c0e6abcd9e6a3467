"""``mosiv view RUN``: an interactive web viewer of a finished run (viser).

``load_run`` reads a run folder into a ``ViewerData`` (no server, no viser import);
``start_viewer`` serves it and returns the running ``Viewer``.
"""

from mosiv_framework.viewer.data import (
    CameraView,
    ObjectSummary,
    ParamComparison,
    Residuals,
    ViewerData,
    load_run,
)


def start_viewer(data: ViewerData, *, host: str = "127.0.0.1", port: int = 8080, frame: int = 0):
    """Serve ``data`` at ``http://host:port`` (the next free port if taken; 0: any free port),
    showing ``frame`` first; returns the running ``viewer.app.Viewer`` (``.url``, ``.stop()``)."""
    from mosiv_framework.viewer.app import Viewer

    return Viewer(data, host=host, port=port, frame=frame)


__all__ = [
    "CameraView",
    "ObjectSummary",
    "ParamComparison",
    "Residuals",
    "ViewerData",
    "load_run",
    "start_viewer",
]
