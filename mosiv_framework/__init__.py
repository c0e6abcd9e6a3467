"""MOSIV: multi-object system identification from video.

Importing this package is cheap on purpose: it loads no simulator backend (warp, taichi) and no
plugin. Plugins are discovered through the registry (``mosiv_framework.registry``) and their
backends are imported lazily inside their factories. Modules log through
``logging.getLogger(__name__)``; the ``mosiv`` command line sets up where records go
(``mosiv_framework.logs``).
"""

from importlib import metadata as _metadata

try:  # one source of truth: the version pyproject.toml gave the installed distribution
    __version__ = _metadata.version("mosiv-framework")
except _metadata.PackageNotFoundError:  # imported from a source tree that is not installed
    __version__ = "0+unknown"
