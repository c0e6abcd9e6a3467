"""The wheels the GPU machine needs to run Genesis' MPM, as ``name==version`` lines.

The GPU machine has PyTorch and a scientific stack but no package index, so genesis-world and
what it imports travel as wheels (benchmarks/stage_device_parts.sh --genesis). Which ones:
genesis-world's requirements, followed recursively through the packages installed here (so the
versions are the ones the tests here ran with), less

- what the GPU machine's image already holds (``GPU_IMAGE``: carrying a second numpy or
  scipy there would shadow the one its PyTorch was built against), and
- what Genesis imports only for work the benchmarks do not ask of it (``NOT_IMPORTED``).

Usage (repository root, in the environment that has ``mosiv-genesis[engine]``)::

    python3 benchmarks/genesis_wheels.py [--skip-present DIR]

``--skip-present DIR`` leaves out the names that already have a wheel in DIR (the small
wheels staged beside warp's), since two versions of one package stop the offline install.
"""

from __future__ import annotations

import argparse
import importlib.metadata as metadata
import re
import sys
from pathlib import Path

from packaging.requirements import Requirement

#: the GPU machine's image: Python 3.12 on Linux x86-64
TARGET = {
    "python_version": "3.12",
    "python_full_version": "3.12.3",
    "platform_system": "Linux",
    "platform_machine": "x86_64",
    "sys_platform": "linux",
    "os_name": "posix",
    "implementation_name": "cpython",
    "platform_python_implementation": "CPython",
    "extra": "",
}
#: packages the GPU machine's image holds (its package list as the device tool documents it),
#: among those genesis-world's requirements reach
GPU_IMAGE = {
    "torch", "triton", "numpy", "scipy", "numba", "llvmlite", "pillow", "psutil", "py-cpuinfo", "scikit-image",
    "networkx", "imageio", "matplotlib", "tqdm", "packaging", "typing-extensions",
    "pyyaml", "requests", "charset-normalizer", "idna", "urllib3", "certifi", "lazy-loader",
    "tifffile", "python-dateutil", "six", "pyparsing", "kiwisolver", "cycler", "fonttools",
    "contourpy", "setuptools", "colorama", "rich", "markdown-it-py", "mdurl", "pygments",
    "mypy-extensions", "typing-inspect", "filelock", "decorator", "opencv-python-headless",
    "absl-py", "etils", "fsspec", "importlib-resources", "zipp", "jinja2", "markupsafe",
    "sympy", "mpmath", "protobuf", "attrs", "flatbuffers", "ml-dtypes", "joblib", "wrapt",
}  # fmt: skip
#: not imported by an MPM scene (checked with sys.modules after building and stepping one):
#: remeshing (pymeshlab, 100 MB), video writing (moviepy, with a 68 MB ffmpeg), PyGEL3D's
#: plots (plotly); and cv2, which the image's opencv-python-headless provides
NOT_IMPORTED = {"pymeshlab", "moviepy", "plotly", "opencv-python"}


def normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def requirement_closure(root: str) -> dict[str, str]:
    """Every package ``root`` needs on the GPU machine, with the version installed here,
    leaving out the image's and the ones not imported (and what only they need)."""
    found: dict[str, str] = {}
    pending = [root]
    while pending:
        name = pending.pop()
        key = normalised(name)
        if key in found or key in GPU_IMAGE or key in NOT_IMPORTED:
            continue
        try:
            found[key] = metadata.version(name)
        except metadata.PackageNotFoundError:
            raise SystemExit(
                f"{name} is not installed here: install mosiv-genesis[engine] first "
                "(pip install -e 'plugins/mosiv-genesis[engine]')"
            ) from None
        for line in metadata.requires(name) or []:
            requirement = Requirement(line)
            if requirement.marker is None or requirement.marker.evaluate(TARGET):
                pending.append(requirement.name)
    return found


def present_names(folder: Path) -> set[str]:
    """The package names of the wheels in ``folder`` (a wheel's name ends at its first dash)."""
    return {normalised(w.name.split("-")[0]) for w in folder.glob("*.whl")}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-present", type=Path, default=None, metavar="DIR")
    args = parser.parse_args(argv)
    closure = requirement_closure("genesis-world")
    skip = present_names(args.skip_present) if args.skip_present else set()
    for name, version in sorted(closure.items()):
        if name not in skip:
            print(f"{name}=={version}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
