"""The command-line flags of every suite that runs on :func:`mosiv_framework.scale.run_tasks`:
``--jobs``, ``--ray-address``, ``--gpus-per-task`` (docs/CLI.md)."""

from __future__ import annotations

import argparse


def add_scale_flags(parser: argparse.ArgumentParser, what: str) -> None:
    """Add the three flags to ``parser``; ``what`` names the suite's tasks in the help."""
    parser.add_argument(
        "--jobs",
        type=int,
        help=f"{what} run at once as Ray tasks (default: 1, one after another in this process, "
        "without --ray-address; as many as the cluster's CPUs and GPUs take with it)",
    )
    parser.add_argument(
        "--ray-address",
        help="run on this Ray cluster (e.g. auto, ray://head:10001) instead of a local Ray",
    )
    parser.add_argument(
        "--gpus-per-task",
        type=float,
        help=f"GPUs each of the {what} asks for: 0.25 lets four share one GPU, 0 hides the "
        "GPUs (default: 1 where the cluster has GPUs, else 0)",
    )


def scale_options(args: argparse.Namespace) -> dict:
    """``run_tasks`` keyword arguments from the flags: ``jobs`` defaults to 1 (this process)
    on one machine and to no limit on a cluster; values checked here, before anything runs."""
    from mosiv_framework.errors import ConfigError

    jobs = args.jobs
    if jobs is None:
        jobs = None if args.ray_address else 1
    elif jobs < 1:
        raise ConfigError(f"--jobs {jobs}: must be at least 1")
    if args.gpus_per_task is not None and args.gpus_per_task < 0:
        raise ConfigError(f"--gpus-per-task {args.gpus_per_task}: must be 0 or more")
    return {"ray_address": args.ray_address, "jobs": jobs, "gpus_per_task": args.gpus_per_task}
