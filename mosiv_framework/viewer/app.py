"""The viser UI of ``mosiv view``: draws a ``ViewerData`` and lets a person scrub its frames.

Scene: predicted particles and reference points per object (object colours, the reference
paler), the scene cameras as frustums, the ground as a grid, a label saying whether the shown
frame was observed or is a prediction of the future, and, when the run was diagnosed, a marker
per object coloured by its residual on that frame. Panel: frame slider, play/pause, toggles, the
identified parameters against the truth, the Chamfer per object and the diagnosis.
"""

from __future__ import annotations

import contextlib
import io
import threading

import numpy as np

from mosiv_framework.viewer import panel
from mosiv_framework.viewer.data import ViewerData


def _point_size(data: ViewerData) -> float:
    """A little under the spacing of the largest object's particles (m): clouds look solid and
    the reference points stay visible between the predicted ones."""
    biggest = max(data.predicted.values(), key=lambda p: p.shape[1])[0]
    extent = float((biggest.max(0) - biggest.min(0)).max())
    return max(0.7 * extent / max(1.0, biggest.shape[0] ** (1.0 / 3.0)), 1e-4)


class Viewer:
    """A running viewer: ``server`` (the viser server), ``url``, ``nodes`` (scene handles by
    name), ``gui`` (panel handles by name); ``show_frame(t)`` moves every view to frame t and
    ``stop()`` ends the server."""

    def __init__(
        self, data: ViewerData, *, host: str = "127.0.0.1", port: int = 8080, frame: int = 0
    ):
        import viser

        self.data = data
        # viser prints a banner of its own on stdout; the command prints the one URL line
        with contextlib.redirect_stdout(io.StringIO()):
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self.nodes: dict[str, object] = {}
        self.gui: dict[str, object] = {}
        self.frame = 0
        self._stopped = threading.Event()
        self._lock = threading.RLock()  # the slider callback re-enters show_frame
        try:
            # served to this machine or a local network: no share button (a public tunnel)
            self.server.gui.configure_theme(control_width="large", show_share_button=False)
            self._build_scene()
            self._build_gui()
            self.show_frame(frame)
        except BaseException:
            self.stop()
            raise
        self._player = threading.Thread(target=self._play_loop, name="mosiv-view-player")
        self._player.daemon = True
        self._player.start()

    # ------------------------------------------------------------------------------ scene
    def _build_scene(self) -> None:
        import viser.transforms as tf

        data, scene = self.data, self.server.scene
        scene.set_up_direction(np.asarray(data.up, dtype=float))
        lower, upper = (np.asarray(c, dtype=float) for c in data.domain)
        size = _point_size(data)
        for k in data.object_ids:
            self.nodes[f"/predicted/obj_{k}"] = scene.add_point_cloud(
                f"/predicted/obj_{k}",
                data.predicted[k][0],
                panel.object_rgb(k),
                point_size=size,
                point_shape="circle",
                precision="float32",
            )
            if k in data.reference:
                self.nodes[f"/reference/obj_{k}"] = scene.add_point_cloud(
                    f"/reference/obj_{k}",
                    data.reference[k][0],
                    panel.object_rgb(k, reference=True),
                    point_size=0.7 * size,
                    point_shape="diamond",
                    precision="float32",
                )
        scale = 0.08 * float(np.linalg.norm(upper - lower))
        for cam in data.cameras:
            self.nodes[f"/cameras/{cam.id}"] = scene.add_camera_frustum(
                f"/cameras/{cam.id}",
                fov=cam.fov_y,
                aspect=cam.aspect,
                scale=scale,
                thickness=1.5,
                thickness_units="screen",
                color=(60, 60, 60),
                wxyz=tf.SO3.from_matrix(cam.rotation).wxyz,
                position=cam.position,
            )
        if data.ground_height is not None and tuple(data.up) == (0.0, 0.0, 1.0):
            width, depth = (upper - lower)[:2]
            self.nodes["/ground"] = scene.add_grid(
                "/ground",
                width=float(width),
                height=float(depth),
                cell_size=float(width) / 8,
                section_size=float(width) / 2,
                position=(*((lower + upper) / 2)[:2], data.ground_height),
            )
        # the phase label floats a little above the highest point the objects reach
        points = np.concatenate([p.reshape(-1, 3) for p in data.predicted.values()])
        up = np.asarray(data.up, dtype=float)
        rise = float((points @ up).max() - points.mean(0) @ up) + 0.1 * float((upper - lower).max())
        self.nodes["/phase"] = scene.add_label(
            "/phase", "", position=points.mean(0) + rise * up, font_screen_scale=1.4
        )
        if data.residuals is not None:
            for k in data.object_ids:
                self.nodes[f"/residual/obj_{k}"] = scene.add_icosphere(
                    f"/residual/obj_{k}", radius=1.5 * size, color=(150, 150, 150)
                )
        self._initial_camera(lower, upper)

    def _initial_camera(self, lower: np.ndarray, upper: np.ndarray) -> None:
        """Look at the objects from the direction of the first scene camera, a little nearer
        (else from beyond a corner of the box)."""
        centre = np.concatenate([p.reshape(-1, 3) for p in self.data.predicted.values()]).mean(0)
        cams = self.data.cameras
        eye = centre + 0.9 * (cams[0].position - centre) if cams else upper + (upper - lower)
        self.server.initial_camera.position = tuple(float(x) for x in eye)
        self.server.initial_camera.look_at = tuple(float(x) for x in centre)

    # -------------------------------------------------------------------------------- gui
    def _build_gui(self) -> None:
        data, gui = self.data, self.server.gui
        with gui.add_folder("Frames"):
            self.gui["frame"] = gui.add_slider(
                "frame", min=0, max=max(data.n_frames - 1, 1), step=1, initial_value=0
            )
            self.gui["play"] = gui.add_checkbox("play", initial_value=False)
            self.gui["status"] = gui.add_markdown(panel.frame_text(data, 0))
        with gui.add_folder("Show"):
            self.gui["show_predicted"] = gui.add_checkbox("predicted particles", True)
            self.gui["show_reference"] = gui.add_checkbox(
                "reference points", bool(data.reference), disabled=not data.reference
            )
            self.gui["show_cameras"] = gui.add_checkbox("cameras", True)
        with gui.add_folder("Identified parameters"):
            for k, obj in sorted(data.objects.items()):
                self.gui[f"params_{k}"] = gui.add_markdown(panel.object_markdown(obj))
            if data.ground_friction is not None:
                gui.add_markdown(f"ground friction: {data.ground_friction:.4g}")
        with gui.add_folder("Chamfer per object"):
            self.gui["chamfer"] = gui.add_markdown(panel.chamfer_markdown(data))
        with gui.add_folder("Diagnosis", expand_by_default=data.residuals is not None):
            self.gui["diagnosis"] = gui.add_markdown(panel.diagnosis_markdown(data))
            if data.residuals is not None and data.residuals.chamfer_mm2:
                self.gui["residual_plot"] = self._residual_plot()
        for note in data.notes:
            gui.add_markdown(f"note: {note}")

        self.gui["frame"].on_update(lambda _: self.show_frame(int(self.gui["frame"].value)))
        for key, prefix in (
            ("show_predicted", "/predicted/"),
            ("show_reference", "/reference/"),
            ("show_cameras", "/cameras/"),
        ):
            self.gui[key].on_update(lambda _, k=key, p=prefix: self._toggle(p, self.gui[k].value))

    def _residual_plot(self):
        """Chamfer residual (mm^2) per object and frame, in the object colours."""
        import viser.uplot as uplot

        res = self.data.residuals
        ids = sorted(res.chamfer_mm2)
        frames = np.arange(max(len(res.chamfer_mm2[k]) for k in ids), dtype=float)
        columns = [np.resize(res.chamfer_mm2[k], frames.shape) for k in ids]
        series = [uplot.Series(label="frame")] + [
            uplot.Series(
                label=f"object {k}",
                stroke="#{:02x}{:02x}{:02x}".format(*panel.object_rgb(k)),
                width=2,
            )
            for k in ids
        ]
        return self.server.gui.add_uplot(
            data=(frames, *columns),
            series=tuple(series),
            title="residual Chamfer per frame (mm²)",
            aspect=1.6,
        )

    def _toggle(self, prefix: str, visible: bool) -> None:
        for name, node in self.nodes.items():
            if name.startswith(prefix):
                node.visible = bool(visible)

    # ----------------------------------------------------------------------------- frames
    def show_frame(self, frame: int) -> None:
        """Move particles, reference points, label and residual markers to ``frame``."""
        data = self.data
        frame = int(min(max(frame, 0), data.n_frames - 1))
        with self._lock:
            self.frame = frame
            for k in data.object_ids:
                pred = data.predicted[k][frame]
                self.nodes[f"/predicted/obj_{k}"].points = pred
                ref = self.nodes.get(f"/reference/obj_{k}")
                if ref is not None:
                    reference = data.reference[k]
                    ref.points = reference[min(frame, reference.shape[0] - 1)]
                marker = self.nodes.get(f"/residual/obj_{k}")
                if marker is not None:
                    self._mark_residual(marker, k, frame, pred)
            phase = data.phase(frame)
            self.nodes["/phase"].text = f"{phase} (frame {frame})"
            self.gui["status"].content = panel.frame_text(data, frame)
            if int(self.gui["frame"].value) != frame:
                self.gui["frame"].value = frame

    def _mark_residual(self, marker, k: int, frame: int, pred: np.ndarray) -> None:
        res = self.data.residuals
        finite = [float(np.nanmax(v)) for v in res.chamfer_mm2.values() if np.isfinite(v).any()]
        value = panel.residual_at(self.data, k, frame)
        marker.color = panel.residual_rgb(value, max(finite, default=0.0))
        up = np.asarray(self.data.up, dtype=float)
        marker.position = tuple(pred.mean(0) + up * float(np.ptp(pred @ up)) * 0.75)

    def _play_loop(self) -> None:
        """While ``play`` is ticked, step one frame per 1/fps s, looping."""
        period = 1.0 / max(self.data.fps, 1e-3)
        while not self._stopped.wait(period):
            if self.gui["play"].value:
                self.show_frame((self.frame + 1) % self.data.n_frames)

    # ------------------------------------------------------------------------------- stop
    def stop(self) -> None:
        """End the server and the player; viser's own 'stopped' line is not printed."""
        if self._stopped.is_set():
            return
        self._stopped.set()
        player = getattr(self, "_player", None)
        if player is not None:
            player.join(timeout=5)
        # viser prints its "stopped" line from its server thread, and its own stop() waits
        # only 1 s for that thread: on a loaded machine the line came after the redirect
        # ended, so the redirect lasts until the thread is gone.
        websock = getattr(self.server, "_websock_server", None)
        server_thread = getattr(websock, "_server_thread", None)
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()
            if server_thread is not None:
                server_thread.join(timeout=30)
