"""``mosiv data show``: the contact sheet holds every camera x frame image at its place, the mask
overlay tints object pixels only, and each camera gets a GIF of all frames at the scene's fps."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from mosiv_framework.cli import data as data_cli
from mosiv_framework.cli.main import main
from mosiv_framework.scene import read_scene
from mosiv_framework.scene.example import write_example_scene

N_FRAMES, N_CAMERAS, SIZE = 4, 3, 24


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return write_example_scene(
        tmp_path_factory.mktemp("show") / "scene", n_frames=N_FRAMES, n_cameras=N_CAMERAS, size=SIZE
    )


def _tile(sheet, row, col):
    y, x = data_cli.tile_origin(row, col, height=SIZE, width=SIZE)
    return sheet[y : y + SIZE, x : x + SIZE]


def test_contact_sheet_places_every_view(scene_dir, tmp_path, capsys):
    out = tmp_path / "preview"
    assert main(["data", "show", str(scene_dir), "--out", str(out)]) == 0
    assert "3 GIF(s)" in capsys.readouterr().out
    sheet = iio.imread(out / "contact_sheet.png")
    scene = read_scene(scene_dir)
    y_end, x_end = data_cli.tile_origin(N_CAMERAS, N_FRAMES, height=SIZE, width=SIZE)
    assert sheet.shape == (y_end, x_end, 3)
    for r, cam in enumerate(scene.camera_ids):
        for t in range(N_FRAMES):
            assert np.array_equal(_tile(sheet, r, t), scene.rgb(cam, t))


def test_mask_overlay_tints_object_pixels_only(scene_dir):
    scene = read_scene(scene_dir)
    plain = data_cli.contact_sheet(scene, masks=False)
    tinted = data_cli.contact_sheet(scene, masks=True)
    cam = scene.camera_ids[0]
    mask = scene.mask(cam, 1)
    assert (mask > 0).any()
    a, b = _tile(plain, 0, 1), _tile(tinted, 0, 1)
    assert np.array_equal(a[mask == 0], b[mask == 0])
    # object pixels move halfway towards their overlay colour
    colour = np.array(data_cli.OVERLAY_COLORS[0], dtype=np.float32)
    expected = 0.5 * a[mask == 1].astype(np.float32) + 0.5 * colour
    assert np.abs(b[mask == 1].astype(np.float32) - expected).max() <= 0.5 + 1e-6


def test_step_keeps_every_step_th_frame(scene_dir):
    scene = read_scene(scene_dir)
    sheet = data_cli.contact_sheet(scene, masks=False, step=3)  # frames 0 and 3
    assert sheet.shape[1] == data_cli.tile_origin(0, 2, height=SIZE, width=SIZE)[1]
    assert np.array_equal(_tile(sheet, 1, 1), scene.rgb(scene.camera_ids[1], 3))


def test_tile_brings_each_frame_down_to_its_longest_side(scene_dir):
    """``tile`` (the import's preview of a large rig): each frame averaged down to ``tile``
    pixels on its longest side, the sheet shrunk alike; a tile above the frames' size changes
    nothing."""
    scene = read_scene(scene_dir)
    half = SIZE // 2
    sheet = data_cli.contact_sheet(scene, masks=False, tile=half)
    assert sheet.shape[:2] == data_cli.tile_origin(N_CAMERAS, N_FRAMES, height=half, width=half)
    y, x = data_cli.tile_origin(1, 2, height=half, width=half)
    frame = scene.rgb(scene.camera_ids[1], 2).astype(np.float32)
    box = frame.reshape(half, 2, half, 2, 3).mean(axis=(1, 3))  # 2 x 2 box average
    assert np.abs(sheet[y : y + half, x : x + half].astype(np.float32) - box).max() <= 1.0
    full = data_cli.contact_sheet(scene, masks=False)
    assert np.array_equal(data_cli.contact_sheet(scene, masks=False, tile=4 * SIZE), full)


def test_one_gif_per_camera_with_all_frames(scene_dir, tmp_path):
    written = data_cli.write_previews(scene_dir, tmp_path / "p", masks=True)
    gifs = sorted(p for p in written if p.suffix == ".gif")
    scene = read_scene(scene_dir)
    assert [g.stem for g in gifs] == scene.camera_ids
    frames = iio.imread(gifs[0], index=None)
    assert frames.shape[:3] == (N_FRAMES, SIZE, SIZE)
    meta = iio.immeta(gifs[0], index=0)
    assert meta["duration"] == pytest.approx(1000.0 / scene.fps, abs=10)  # ms, GIF has 10 ms ticks
    # GIF keeps the picture up to palette quantisation
    first = data_cli.overlay_masks(
        scene.rgb(scene.camera_ids[0], 0), scene.mask(scene.camera_ids[0], 0)
    )
    assert np.abs(frames[0][..., :3].astype(int) - first.astype(int)).mean() < 8


def test_show_rejects_a_bad_step(scene_dir, tmp_path, capsys):
    assert main(["data", "show", str(scene_dir), "--out", str(tmp_path), "--step", "0"]) == 2
    assert "--step=0" in capsys.readouterr().err
