"""The ground truth of a benchmark capture, carried into the scene imported from it.

``mosiv data capture --with-reference`` copies the scene's gt/ beside the capture (in the
scene's own frame: metres, z up, frame 0 = the scene's first frame). An import puts the scene in
a frame of its own: the capture's rig frame (``capture.json``: units, up) mapped by the import's
alignment (``import.json``: scale, rotation, offset, the ground fitted or given) and cut to a
common time base (``import.json``: frames dropped per camera; ``capture.json``: frames each
camera started late). ``attach_reference`` composes both and writes the reference as the imported
scene's gt/, so ``mosiv run`` scores an imported scene as it scores the original one: positions
and initial velocities transformed (a velocity is left out where the imported scene starts
later than the original: it was not recorded there), material parameters (frame-free) copied.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from mosiv_framework.capture.align import Alignment, RigFrame
from mosiv_framework.capture.common import CaptureError


def reference_transform(capture: dict, record: dict) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) with imported point = A @ original point + b, from capture.json and import.json.

    A original point p (m, z up) is ``rig.scale * M p`` in the rig's world; the import maps a
    rig point q to ``alignment.scale * Q q + offset``."""
    rig = RigFrame(capture["units"], capture["up"])
    a = record["alignment"]
    align = Alignment(float(a["scale"]), np.asarray(a["rotation"]), np.asarray(a["offset"]))
    linear = align.scale * rig.scale * align.rotation @ rig.rotation
    return linear, align.offset.copy()


def reference_shift(capture: dict, record: dict) -> int:
    """The original frame that the imported scene's frame 0 shows: each camera's late start
    plus the frames the import dropped from it, which must agree over the cameras the import
    kept (``--late-cameras drop`` leaves the late ones out; ``keep`` starts the clip with the
    camera that started first, the largest offset less the smallest before the others')."""
    left_out = set(record.get("late_cameras_left_out") or [])
    offsets = {c: int(o) for c, o in record["offsets"].items()}
    earlier = 0
    if record.get("settings", {}).get("late_cameras") == "keep" and offsets:
        earlier = max(offsets.values()) - min(offsets.values())
    starts = {
        c["id"]: int(c["start_frame"]) + offsets[c["id"]] - earlier
        for c in capture["cameras"]
        if c["id"] not in left_out
    }
    if len(set(starts.values())) != 1:
        raise CaptureError(
            f"the import's time offsets do not undo the capture's late starts: the imported "
            f"frame 0 shows original frames {starts} (camera -> frame); give --offsets"
        )
    return next(iter(starts.values()))


def attach_reference(capture_dir: str | Path, scene_dir: str | Path) -> Path:
    """Write ``capture_dir/reference_gt`` into ``scene_dir/gt`` in the imported frame; returns
    the gt folder. CaptureError when the capture has no reference, the scene already has gt/,
    or the objects (ids, materials) or frames do not correspond."""
    capture_dir, scene_dir = Path(capture_dir), Path(scene_dir)
    capture = json.loads((capture_dir / "capture.json").read_text())
    record = json.loads((scene_dir / "import.json").read_text())
    scene = json.loads((scene_dir / "scene.json").read_text())
    source = capture_dir / capture.get("reference_gt", {}).get("path", "reference_gt")
    if not (source / "points.npz").is_file():
        raise CaptureError(f"{capture_dir}: no reference_gt/ (write it with --with-reference)")
    gt = scene_dir / "gt"
    if gt.exists():
        raise CaptureError(f"{gt}: exists already; nothing is overwritten")
    linear, offset = reference_transform(capture, record)
    shift, n = reference_shift(capture, record), int(scene["n_frames"])
    params = json.loads((source / "params.json").read_text())
    with np.load(source / "points.npz", allow_pickle=False) as data:
        points = {key: data[key] for key in data.files}
    if any(len(p) < shift + n for p in points.values()):
        raise CaptureError(f"{source}: fewer than {shift + n} frames; not this capture's scene")
    moved = {
        int(key.removeprefix("obj_")): (
            p[shift : shift + n].astype(np.float64) @ linear.T + offset
        ).astype(np.float32)
        for key, p in points.items()
    }
    ids = match_objects(scene_dir, moved)  # imported id -> reference id
    materials = {int(o["id"]): o["material"] for o in scene["objects"]}
    truth = {int(o["id"]): o for o in params["objects"]}
    wrong = {k: (materials[k], truth[r]["material"]) for k, r in ids.items()
             if materials[k] != truth[r]["material"]}  # fmt: skip
    if wrong:
        raise CaptureError(
            f"{scene_dir}: imported objects have other materials than the reference objects "
            f"they show (id: (imported, reference)): {wrong}; give the materials in the "
            "segmenter's order (--objects FILE names them by id)"
        )
    params["objects"] = [dict(truth[r], id=k) for k, r in sorted(ids.items())]
    for obj in params["objects"]:
        if "initial_velocity" not in obj:
            continue
        if shift:  # the velocity at a later frame is not recorded (gravity, contacts)
            del obj["initial_velocity"]
        else:  # velocities see the linear part only
            obj["initial_velocity"] = (linear @ np.asarray(obj["initial_velocity"])).tolist()
    params["reference"] = {
        "capture": str(capture_dir),
        "frame_shift": shift,
        "object_ids": {str(k): r for k, r in ids.items()},  # imported -> reference
    }
    gt.mkdir()
    np.savez(gt / "points.npz", **{f"obj_{k}": moved[r] for k, r in ids.items()})
    (gt / "params.json").write_text(json.dumps(params, indent=2) + "\n")
    for extra in ("effects.json",):
        if (source / extra).is_file():
            shutil.copy2(source / extra, gt / extra)
    return gt


def match_objects(scene_dir: Path, points: dict[int, np.ndarray]) -> dict[int, int]:
    """Imported object id -> reference object id, the one whose points (imported frame) fall in
    that object's masks at the first frame, over every camera. CaptureError unless the matching
    is one to one with most points inside (an import's segmenter numbers objects its own way)."""
    import torch

    from mosiv_framework.scene import read_scene

    scene = read_scene(scene_dir)
    refs = sorted(points)
    if len(refs) != len(scene.object_ids):
        raise CaptureError(
            f"{scene_dir}: {len(scene.object_ids)} objects imported, the reference has {len(refs)}"
        )
    hits = np.zeros((len(scene.object_ids), len(refs)))
    for cam in scene.cameras_at(0):
        mask = np.asarray(scene.mask(cam.id, 0))
        for j, ref in enumerate(refs):
            uv, z = cam.project(torch.from_numpy(points[ref][0].astype(np.float64)))
            px = np.floor(uv.numpy()).astype(int)
            inside = (px >= 0).all(1) & (px[:, 0] < cam.width) & (px[:, 1] < cam.height)
            px = px[inside & (z.numpy() > 0)]
            labels = mask[px[:, 1], px[:, 0]]
            for i, oid in enumerate(scene.object_ids):
                hits[i, j] += float(np.mean(labels == oid)) if labels.size else 0.0
    hits /= len(scene.cameras_at(0))
    best = {oid: refs[int(np.argmax(hits[i]))] for i, oid in enumerate(scene.object_ids)}
    overlap = hits.max(axis=1)
    if len(set(best.values())) != len(best) or np.any(overlap < 0.5):
        raise CaptureError(
            f"{scene_dir}: imported objects and reference objects do not correspond (imported "
            f"id -> reference id by mask overlap: {best}, overlaps {np.round(overlap, 2)})"
        )
    return best
