"""Peak memory of ``mosiv data import`` against the size of the frames it imports.

Writes the two-sphere example scene (``--cameras``, ``--frames``, ``--size`` pixels square),
turns it into a capture as a rig delivers it (``mosiv data capture``: H.264 videos through a
lens, COLMAP cameras in cm with y up, clean plates), and imports it with the classical
segmenter in a child process of its own, whose peak resident memory (``ru_maxrss``) is read
there. A second child that loads the same modules and imports nothing gives the baseline (the
Python, torch and MOSIV modules). The figure of merit is the import's own peak over the bytes of
its frames as uint8 RGB: the frames themselves are held in memory (docs/SCENE_FORMAT.md), so 1
is the floor and anything above it is working memory.

    python benchmarks/import_memory.py --out OUT [--cameras 4 --frames 48 --size 512]

Prints one JSON row and writes it to OUT/import_memory.json (OUT must be new or empty).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def peak_rss_mb() -> float:
    """This process's peak resident memory in MB (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def child(argv: list[str]) -> int:
    """Run ``mosiv data import ARGV`` here (or, with no ARGV, only load what it loads) and print
    the peak memory as the last line of stdout."""
    from mosiv_framework.cli.main import main as mosiv
    from mosiv_framework.segment import classical  # noqa: F401  (loaded by the import too)

    code = mosiv(["data", "import", *argv]) if argv else 0
    print(json.dumps({"peak_rss_mb": peak_rss_mb(), "code": code}))
    return int(code or 0)


def measure(argv: list[str]) -> dict:
    """Peak memory (MB) and wall time (s) of one child process."""
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--child", *argv],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise SystemExit(f"the import failed:\n{done.stderr[-3000:]}")
    row = json.loads(done.stdout.strip().splitlines()[-1])
    return {"peak_rss_mb": row["peak_rss_mb"], "wall_s": time.perf_counter() - start}


def frame_bytes(scene: Path) -> int:
    """Bytes of the imported scene's frames as uint8 RGB, every camera and frame."""
    from mosiv_framework.scene import read_scene

    read = read_scene(scene)
    return sum(c.width * c.height for c in read.cameras) * 3 * read.n_frames


def code_version() -> str:
    """The commit of the mosiv_framework that runs (PYTHONPATH may point at another checkout)."""
    import mosiv_framework

    where = Path(mosiv_framework.__file__).resolve().parent
    done = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=where
    )
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--", "."], capture_output=True, text=True, cwd=where
    )
    version = done.stdout.strip() or "unknown"
    return version + ("+modified" if dirty.stdout.strip() else "")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        return child(argv[1:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="new or empty folder")
    parser.add_argument("--cameras", type=int, default=4)
    parser.add_argument("--frames", type=int, default=48)
    parser.add_argument("--size", type=int, default=512, help="pixels, square frames")
    args = parser.parse_args(argv)
    if args.out.exists() and any(args.out.iterdir()):
        raise SystemExit(f"--out {args.out}: not empty; give a new folder")
    from mosiv_framework.scene.example import write_example_scene

    scene, capture, imported = args.out / "scene", args.out / "capture", args.out / "imported"
    print(f"[import-memory] writing the example scene {args.cameras} x {args.frames} frames")
    write_example_scene(scene, n_frames=args.frames, n_cameras=args.cameras, size=args.size)
    rig = ["--units", "cm", "--up", "y", "--distortion=-0.05,0.01", "--background-plate"]
    subprocess.run(
        [sys.executable, "-m", "mosiv_framework.cli.main", "data", "capture", *rig,
         str(scene), str(capture)],
        check=True, capture_output=True,
    )  # fmt: skip
    print("[import-memory] importing (child process)")
    baseline = measure([])
    objects = json.loads((scene / "scene.json").read_text(encoding="utf-8"))["objects"]
    materials = ",".join(o["material"] for o in sorted(objects, key=lambda o: o["id"]))
    run = measure([str(imported), "--recording", str(capture), "--materials", materials,
                   "--units", "cm", "--up", "y", "--offsets", "none"])  # fmt: skip
    frames_mb = frame_bytes(imported) / 2**20
    own = run["peak_rss_mb"] - baseline["peak_rss_mb"]
    row = {
        "cameras": args.cameras,
        "frames": args.frames,
        "size": args.size,
        "frames_mb": round(frames_mb, 1),
        "baseline_rss_mb": round(baseline["peak_rss_mb"], 1),
        "import_peak_rss_mb": round(run["peak_rss_mb"], 1),
        "import_own_mb": round(own, 1),
        "own_over_frames": round(own / frames_mb, 2),
        "wall_s": round(run["wall_s"], 1),
        "code": code_version(),
    }
    (args.out / "import_memory.json").write_text(json.dumps(row, indent=2) + "\n")
    print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
