"""Peak memory of ``mosiv data import`` against the size of the frames it imports.

Writes the two-sphere example scene (``--cameras``, ``--frames``, ``--size`` pixels square),
turns it into a capture as a rig delivers it (``mosiv data capture``: H.264 videos through a
lens, COLMAP cameras in cm with y up, clean plates), and imports it with the classical
segmenter in a child process of its own, whose peak resident memory (VmHWM) is read there.
The same import of the same rig at 16 frames of 64 pixels, in a child of its own, gives
the baseline (the modules it loads: Python, torch, MOSIV, ffmpeg). The figure of merit is the import's own peak over the bytes of
its frames as uint8 RGB: the frames themselves are held in memory (docs/SCENE_FORMAT.md), so 1
is the floor and anything above it is working memory.

    python benchmarks/import_memory.py --out OUT [--cameras 4 --frames 48 --size 512]

Prints one JSON row and writes it to OUT/import_memory.json (OUT must be new or empty).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def peak_rss_mb() -> float:
    """This process's peak resident memory in MB (its own: ``peak_rss_bytes``)."""
    from mosiv_framework.pipeline.memory import peak_rss_bytes

    return peak_rss_bytes() / 2**20


def child(argv: list[str]) -> int:
    """Run ``mosiv data import ARGV`` here and print the peak memory as the last line of
    stdout."""
    from mosiv_framework.cli.main import main as mosiv

    code = mosiv(["data", "import", *argv])
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


def write_capture(folder: Path, cameras: int, frames: int, size: int) -> tuple[Path, str]:
    """The example scene in ``folder``/scene and its rig capture in ``folder``/capture; returns
    (the capture, its objects' materials as ``--materials`` takes them)."""
    from mosiv_framework.scene.example import write_example_scene

    scene, capture = folder / "scene", folder / "capture"
    write_example_scene(scene, n_frames=frames, n_cameras=cameras, size=size)
    rig = ["--units", "cm", "--up", "y", "--distortion=-0.05,0.01", "--background-plate"]
    subprocess.run(
        [sys.executable, "-m", "mosiv_framework.cli.main", "data", "capture", *rig,
         str(scene), str(capture)],
        check=True, capture_output=True,
    )  # fmt: skip
    objects = json.loads((scene / "scene.json").read_text(encoding="utf-8"))["objects"]
    return capture, ",".join(o["material"] for o in sorted(objects, key=lambda o: o["id"]))


def import_args(capture: Path, out: Path, materials: str) -> list[str]:
    """``mosiv data import`` of a capture written by ``write_capture``."""
    return [str(out), "--recording", str(capture), "--materials", materials,
            "--units", "cm", "--up", "y", "--offsets", "none"]  # fmt: skip


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
    print(f"[import-memory] writing the example scene {args.cameras} x {args.frames} frames")
    capture, materials = write_capture(args.out / "full", args.cameras, args.frames, args.size)
    # the baseline: the same import of the same rig at 16 frames of 64 pixels, which loads every
    # module the full import loads and holds next to nothing
    tiny, _ = write_capture(args.out / "tiny", args.cameras, 16, 64)
    print("[import-memory] importing (child processes)")
    baseline = measure(import_args(tiny, args.out / "tiny" / "imported", materials))
    imported = args.out / "full" / "imported"
    run = measure(import_args(capture, imported, materials))
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
