"""Every table of docs/RESULTS.md from one command: the three benchmark suites, then one file.

Runs, into sub-folders of ``--out`` (each suite resumes what it finished before):

1. ``identify_suite.py``: the oracle pipeline against the discrete-library baseline on the ten
   material pairs (parameter errors, observed / future CD, time and peak memory per scene);
2. ``video_suite.py``: the from-video pipeline on the same scenes with the six supervision
   variants (PSNR, SSIM, CD, EMD per pair; the ablation of paper table 3);
3. ``noise_suite.py``: sensitivity to i.i.d. and shared reconstruction noise (paper appendix);

then concatenates their ``table.md`` files, under the command that made each, into
``--out/tables.md``. ``--size tiny`` is the CPU protocol of RESULTS (48 px, 4 cameras, 14
frames of which 9 observed; a few hours on 2 cores); ``--size paper`` the paper's (GPU).

    python benchmarks/results.py --size tiny --out runs/results --jobs 2
    python3 benchmarks/results.py --size paper --out runs/results --jobs 4
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: per protocol: (identification recipe, from-video recipe, overrides for every run)
PROTOCOLS = {
    "tiny": (
        "recipes/quickstart.yaml",
        "recipes/video_quickstart.yaml",
        ["scene.source.n_frames=14", "scene.source.observed_frames=9"],
    ),
    "paper": ("recipes/paper.yaml", "recipes/video_paper.yaml", []),
}
VARIANTS = "object-cd-sil,object-cd,object-sil,scene-cd-sil,scene-cd,scene-sil"


def commands(size: str, out: Path, jobs: int) -> list[tuple[str, list[str]]]:
    """(title, argv) of each suite, in the order they run."""
    ident, video, overrides = PROTOCOLS[size]
    py = sys.executable
    return [
        (
            "Identification: oracle against the library baseline",
            [
                py,
                str(HERE / "identify_suite.py"),
                "--recipe",
                ident,
                "--out",
                str(out / "identify"),
                "--jobs",
                str(jobs),
                *overrides,
            ],
        ),
        (
            "From video: six supervision variants",
            [
                py,
                str(HERE / "video_suite.py"),
                "--recipe",
                video,
                "--out",
                str(out / "video"),
                "--jobs",
                str(jobs),
                "--variants",
                VARIANTS,
                *overrides,
            ],
        ),
        (
            "Sensitivity to reconstruction noise",
            [
                py,
                str(HERE / "noise_suite.py"),
                "--recipe",
                ident,
                "--out",
                str(out / "noise"),
                "--jobs",
                str(jobs),
                *overrides,
            ],
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", choices=sorted(PROTOCOLS), default="tiny")
    ap.add_argument("--out", type=Path, default=Path("runs/results"))
    ap.add_argument("--jobs", type=int, default=1, help="parallel runs inside each suite")
    ap.add_argument("--dry-run", action="store_true", help="print the suites' commands only")
    args = ap.parse_args(argv)
    if args.dry_run:
        for title, argv_ in commands(args.size, args.out, args.jobs):
            print(f"# {title}\n{' '.join(argv_)}")
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    sections = [f"# MOSIV result tables ({args.size} protocol)\n"]
    failed = []
    for (title, argv_), folder in zip(
        commands(args.size, args.out, args.jobs), ("identify", "video", "noise")
    ):
        print(f"[results] {title}: {' '.join(argv_)}", flush=True)
        code = subprocess.call(argv_)
        table = args.out / folder / "table.md"
        if code != 0:
            failed.append(f"{title} (exit {code})")
        body = table.read_text() if table.is_file() else "(no table: the suite did not finish)\n"
        sections.append(f"## {title}\n\n```\n{' '.join(argv_)}\n```\n\n{body}")
    (args.out / "tables.md").write_text("\n".join(sections))
    print(f"[results] tables in {args.out / 'tables.md'}")
    if failed:
        print(f"[results] failed: {'; '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
