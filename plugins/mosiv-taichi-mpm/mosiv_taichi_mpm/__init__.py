"""MOSIV simulator plugin: differentiable multi-object MLS-MPM on Taichi.

Importing this package does not import taichi; the simulator module does, on first use.
"""

import os

# Taichi prints its version banner on stdout when it is first imported, which would corrupt
# machine-readable output such as `mosiv bench sim --json`; a user who wants it sets the
# variable to true. This must run before any submodule imports taichi.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "false")

from mosiv_taichi_mpm.options import TaichiMPMOptions  # noqa: E402

__all__ = ["TaichiMPMOptions"]
