"""``mosiv export`` (a run as PLY, 3DGS splats, glTF meshes, JSON) and ``mosiv data capture``
(a scene written as a capture rig delivers it: videos, COLMAP cameras, lens distortion)."""

from __future__ import annotations

from mosiv_framework.errors import ConfigError


def add_parser(sub) -> None:
    p = sub.add_parser(
        "export",
        help="write a finished run as per-frame PLY (particles, 3DGS Gaussians), glTF meshes "
        "and parameter JSON",
    )
    p.add_argument("run_dir", help="a folder written by `mosiv run`")
    p.add_argument(
        "--out",
        help="export folder (default: RUN_DIR/export); new, empty or a previous export",
    )
    p.add_argument(
        "--frames",
        default="all",
        help="all (default), observed, or N..M (frames N to M, both included)",
    )
    p.add_argument(
        "--up",
        default="z",
        choices=["z", "y", "-y"],
        help="the up axis of the PLY files' world: z (MOSIV's, default), y, or -y (y down, as "
        "splat viewers made for COLMAP captures expect); glTF meshes are always y up",
    )
    p.set_defaults(handler=run_export)


def add_capture_parser(dsub) -> None:
    """``data capture`` under the ``data`` command's sub-parsers ``dsub``."""
    # the choices only: the capture package itself loads pycolmap and imageio when it runs
    from mosiv_framework.capture.options import AXES, DEFAULT_CRF, METRES_PER_UNIT, WRITE_MODELS

    p = dsub.add_parser(
        "capture",
        help="write a scene as a capture rig delivers it: H.264 videos, COLMAP text cameras, "
        "lens distortion, no masks or ground truth",
    )
    p.add_argument("scene_dir")
    p.add_argument("out_dir", help="capture folder to write (new or empty)")
    p.add_argument(
        "--units", default="m", choices=sorted(METRES_PER_UNIT), help="rig units (default m)"
    )
    p.add_argument("--up", default="z", choices=sorted(AXES), help="rig world up axis (default z)")
    p.add_argument(
        "--distortion",
        help="lens coefficients k1,k2 or k1,k2,p1,p2 of the OpenCV model, or "
        "fisheye:k1[,k2[,k3[,k4]]] of a fisheye lens (with --camera-model OPENCV_FISHEYE; "
        "default none); a negative first one needs '=': --distortion=-0.2,0.05",
    )
    p.add_argument(
        "--camera-model",
        default=None,
        choices=WRITE_MODELS,
        help="COLMAP camera model of cameras.txt (RADIAL needs fx = fy and only k1, k2; "
        "OPENCV_FISHEYE holds a fisheye lens; default OPENCV, or OPENCV_FISHEYE for a fisheye "
        "--distortion)",
    )
    p.add_argument(
        "--crf", type=int, default=DEFAULT_CRF, help=f"H.264 quality 0..51 (default {DEFAULT_CRF})"
    )
    p.add_argument(
        "--pixel-format",
        default="yuv420p",
        choices=["yuv420p", "yuv444p"],
        help="H.264 pixel format: yuv420p (default, as cameras record) keeps the colour at half "
        "resolution, yuv444p whole",
    )
    p.add_argument(
        "--offsets",
        help="leading frames to drop per camera, e.g. cam_01=2,cam_02=1 (unsynchronised start)",
    )
    p.add_argument(
        "--with-reference",
        action="store_true",
        help="copy the scene's gt/ to OUT/reference_gt/ for benchmarking an importer",
    )
    p.add_argument(
        "--background-plate",
        action="store_true",
        help="write OUT/background/<camera>.png, the empty scene through the lens, as a rig "
        "records a clean plate before the take (made from the frames outside the scene's masks)",
    )
    p.set_defaults(handler=run_capture)


def run_export(args) -> int:
    from mosiv_framework.export import export_run

    out = export_run(args.run_dir, args.out, args.frames, up=args.up)
    print(out)
    return 0


def run_capture(args) -> int:
    from mosiv_framework.capture import Distortion, RigFrame, write_capture

    try:
        distortion = Distortion.parse(args.distortion) if args.distortion else Distortion()
    except ValueError as exc:
        raise ConfigError(f"--distortion: {exc}") from None
    out = write_capture(
        args.scene_dir,
        args.out_dir,
        rig=RigFrame(args.units, args.up),
        distortion=distortion,
        camera_model=args.camera_model
        or ("OPENCV_FISHEYE" if distortion.model == "fisheye" else "OPENCV"),
        crf=args.crf,
        offsets=args.offsets,
        with_reference=args.with_reference,
        pixel_format=args.pixel_format,
        with_plates=args.background_plate,
    )
    print(out)
    return 0
