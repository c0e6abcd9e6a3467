"""Load a script of a folder that is not a package (benchmarks/) as a module, for tests.

The benchmark scripts import their sibling scripts by plain name (``from genesis_identify
import ...``), as they do when run from benchmarks/, so the folder is put on ``sys.path`` while
the script loads; pytest's ``--import-mode=importlib`` would otherwise leave it off.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_script(path: Path, *, register: bool = False, keep_path: bool = False) -> ModuleType:
    """The script at ``path`` executed as a module named after its file.

    Args:
        path: the script (``benchmarks/NAME.py``).
        register: also put the module in ``sys.modules`` under its name (dataclasses and
            pickling look their module up there).
        keep_path: leave the script's folder on ``sys.path`` afterwards, for scripts that
            import their siblings inside functions, at call time.

    Returns:
        The loaded module.
    """
    path = Path(path)
    folder = str(path.parent)
    added = folder not in sys.path
    if added:
        sys.path.insert(0, folder)
    try:
        spec = importlib.util.spec_from_file_location(path.stem, path)
        if spec is None or spec.loader is None:
            raise ImportError(f"{path}: not a Python script that can be loaded")
        module = importlib.util.module_from_spec(spec)
        if register:
            sys.modules[path.stem] = module
        spec.loader.exec_module(module)
    finally:
        if added and not keep_path:
            sys.path.remove(folder)
    return module
