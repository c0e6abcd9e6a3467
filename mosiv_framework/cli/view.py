"""``mosiv view RUN``: serve an interactive 3D viewer of a finished run folder (viser).

Prints the address and serves until Ctrl-C (the command line then ends with status 130 and one
line); ``--no-block`` starts the server, prints the address and returns at once (for scripts
and tests, which stop the server themselves through ``mosiv_framework.viewer``).
"""

from __future__ import annotations


def add_parser(sub) -> None:
    view = sub.add_parser(
        "view",
        help="interactive 3D viewer of a finished run: frames, reference vs prediction, "
        "cameras, identified parameters, diagnosis residuals",
    )
    view.add_argument("run_dir", help="a folder written by `mosiv run`")
    view.add_argument(
        "--port", type=int, default=8080, help="port to serve on (the next free one if taken)"
    )
    view.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: every "
        "network interface)",
    )
    view.add_argument("--frame", type=int, default=0, help="the frame shown first (default 0)")
    view.add_argument(
        "--no-block",
        action="store_true",
        help="start the server, print its address and return instead of serving until Ctrl-C "
        "(for Python code calling mosiv_framework.cli.main.main, which keeps the server running)",
    )
    view.set_defaults(handler=view_run)


def view_run(args):
    """Load the run, serve it; blocks until Ctrl-C unless ``--no-block``. Returns the exit
    status (0); with ``--no-block`` the running viewer is kept on ``args.viewer``."""
    import threading

    from mosiv_framework.errors import ConfigError
    from mosiv_framework.viewer import load_run, start_viewer

    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: give a port number from 0 to 65535 (0: any free)")
    data = load_run(args.run_dir)
    if not 0 <= args.frame < data.n_frames:
        raise ConfigError(f"--frame {args.frame}: the run has frames 0 to {data.n_frames - 1}")
    viewer = start_viewer(data, host=args.host, port=args.port, frame=args.frame)
    print(f"viewing {args.run_dir} at {viewer.url}" + ("" if args.no_block else " (Ctrl-C stops)"))
    if args.no_block:
        args.viewer = viewer
        return 0
    try:
        threading.Event().wait()  # until Ctrl-C raises KeyboardInterrupt here
    finally:
        viewer.stop()
    return 0
