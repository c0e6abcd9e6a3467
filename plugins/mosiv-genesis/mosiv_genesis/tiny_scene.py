"""Make the tiny Genesis scenes the tests read (tests/data/tiny_scene, vortex_scene, contact_scene).

    python -m mosiv_genesis.tiny_scene plugins/mosiv-genesis/tests/data/tiny_scene
    python -m mosiv_genesis.tiny_scene plugins/mosiv-genesis/tests/data/vortex_scene --vortex
    python -m mosiv_genesis.tiny_scene plugins/mosiv-genesis/tests/data/contact_scene --contact

Two cameras, six frames of 32 x 32 pixels, coarse particles on a coarse grid, the wide ranges
(seed 15 draws a stiff sand, E 8.6e5 Pa, so the substeps are raised from 70 to 89): the folder
stays well under 300 KB and lets every test that reads a Genesis recording run without the
engine installed. About 25 s on 2 CPU cores once Genesis' kernels are cached (5 min before).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

#: the options of the committed scene (the tests check gt/params.json against them)
TINY_OPTIONS = {
    "resolution": 32,
    "n_cameras": 2,
    "n_frames": 6,
    "observed_frames": 4,
    "collision_frame": 3,
    "grid_density": 32.0,
    "substeps": 70,
    "particle_size": 0.015,
    "materials": "elastic,sand",
    "shapes": "apple,barrel",
    "ranges": "wide",
    "seed": 15,
    "progress": False,
}
#: the committed scene with a concealed out-of-library vortex (about 30 KB): one camera of
#: 16 x 16 pixels, two elastic bodies in free flight for six frames before they meet at frame
#: 6, so their measured accelerations can be checked against the recorded field without the
#: engine (tests/test_genesis_fields.py)
VORTEX_OPTIONS = {
    "resolution": 16,
    "n_cameras": 1,
    "n_frames": 8,
    "observed_frames": 6,
    "collision_frame": 6,
    "grid_density": 32.0,
    "substeps": 70,
    "particle_size": 0.015,
    "materials": "elastic,elastic",
    "shapes": "apple,barrel",
    "seed": 2,
    "progress": False,
    "conceal": "vortex:strength=12",
}
#: the committed scene whose bodies meet early (about 60 KB): two plasticine bodies (paper
#: ranges: E about 5e4 Pa, yield stress 4-5 kPa) collide at frame 2 and stay within one Genesis
#: grid cell of each other through the last observed frame (6), so identification can tell the
#: contact mode from the data (tests/test_genesis_contact_choice.py). Plastic bodies, because
#: two elastic ones thrown the same way bounce apart after one frame in Genesis too.
CONTACT_OPTIONS = {
    "resolution": 32,
    "n_cameras": 2,
    "n_frames": 8,
    "observed_frames": 7,
    "collision_frame": 2,
    "grid_density": 32.0,
    "substeps": 70,
    "particle_size": 0.015,
    "materials": "plasticine,plasticine",
    "shapes": "apple,barrel",
    "ranges": "paper",
    "seed": 0,
    "progress": False,
}
#: the scenes main() can write, by flag
SCENES = {"tiny": TINY_OPTIONS, "vortex": VORTEX_OPTIONS, "contact": CONTACT_OPTIONS}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", help="new or empty folder to write the scene into")
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--vortex", action="store_true", help="the scene with a concealed vortex instead"
    )
    which.add_argument(
        "--contact", action="store_true", help="the scene whose bodies meet early instead"
    )
    args = parser.parse_args(argv)
    from mosiv_framework.registry import get_registry

    start = time.perf_counter()
    options = SCENES["vortex" if args.vortex else "contact" if args.contact else "tiny"]
    source = get_registry().create("scene_source", "genesis", dict(options))
    path = source.generate(Path(args.out_dir))
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    print(f"wrote {path} ({size / 1024:.0f} KB) in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
