"""MOSIV: multi-object system identification from video.

Importing this package is cheap on purpose: it loads no simulator backend (warp, taichi) and no
plugin. Plugins are discovered through the registry (``mosiv_framework.registry``) and their
backends are imported lazily inside their factories.
"""

__version__ = "0.1.0"
