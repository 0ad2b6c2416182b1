"""``phirie view OUT_DIR``: a converted scene in the browser, live (viser; the ``viewer`` extra).

Scene nodes (``view.scene`` makes their arrays):

* ``/background``: the background Gaussians (``background.ply``), one splat node;
* ``/objects/<id>``: a frame per object carrying its motion since t = 0 (S_i(t) S_i(0)⁻¹); under it
  ``splats`` (its Gaussians placed at t = 0, sent once), ``mesh`` (the completed mesh),
  ``collision/part_NN`` (its convex parts, semi-transparent in its instance colour) and
  ``grab/part_NN`` (the parts shrunk inside the Gaussians at opacity 0: what a drag picks);
* ``/source``: the capture's own Gaussians in the world frame (before conversion), sent when first
  shown;
* ``/cameras/<k>``: the capture's camera frustums; clicking one moves the view to it.

MuJoCo C steps on the server (``view.live.LiveScene``); an update thread advances it in real time
and moves the object frames. A click shoots the object under the pointer along the view ray; a
drag on an object pulls it towards the pointer. The panel: play / pause / reset, the shot speed,
toggles (collision parts, completed meshes, instance colours, source capture vs converted scene,
background only, cameras) and one folder per object from ``manifest.json`` (``view.panel``).
No GPU is needed on the server: the browser draws.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from phirie_jax import layout
from phirie_jax.errors import SceneInputError
from phirie_jax.interact.environment import Environment
from phirie_jax.io.mesh import read_mesh
from phirie_jax.manifest import Manifest
from phirie_jax.report.renders import source_gaussians
from phirie_jax.view.config import ViewConfig
from phirie_jax.view.live import LiveScene
from phirie_jax.view.panel import object_markdown
from phirie_jax.view.scene import (
    SplatArrays,
    camera_view,
    palette_colour,
    placed_vertices,
    splat_arrays,
)

MISSING_VISER = "viser is not importable (install the viewer extra: pip install 'phirie_jax[viewer]')"
COLLISION_OPACITY = 0.45
GRAB_SHRINK = 0.75     # a drag handle is the convex parts scaled by this about their centre
MESH_COLOUR = (200, 200, 205)
FRUSTUM_LINE_PX = 1.5  # thin at any distance: the view starts inside camera 0's own frustum
STATUS_PERIOD = 0.25   # s between updates of the panel's time readout


def _viser():
    try:
        import viser
    except ImportError:
        raise SceneInputError(None, "viewer", MISSING_VISER) from None
    return viser


class Viewer:
    """The viewer of one converted folder, serving until ``close`` (module docstring)."""

    def __init__(self, out_dir: str | Path, config: ViewConfig = ViewConfig()):
        viser = _viser()
        self.out_dir = Path(out_dir)
        self.config = config
        self.manifest = Manifest.load_or_create(self.out_dir)
        self.entries = {o.id: o for o in self.manifest.objects()}
        env = Environment.load(self.out_dir)
        self.live = LiveScene(env, config)
        placed = splat_arrays(env.gaussians())        # background rows first, then each object's
        background_num = env.background.num
        self.background = placed.rows(slice(0, background_num))
        self.objects = {o.id: placed.rows(slice(background_num + o.gaussians.start, background_num + o.gaussians.stop))
                        for o in env.objects}
        self.views = [camera_view(c) for c in env.cameras]
        self._source: SplatArrays | None = None
        self.server = viser.ViserServer(host=config.host, port=config.port, verbose=False)
        self.server.gui.configure_theme(control_width="medium", show_share_button=False)
        self.server.scene.set_up_direction("+z")
        self._nodes: dict[str, object] = {}
        self._instance_colours = False
        self._build_scene()
        self._build_panel()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._update_loop, name="phirie-view", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.server.stop()

    # --- the scene ----------------------------------------------------------------------

    def _splats(self, name: str, arrays: SplatArrays, visible: bool = True):
        return self.server.scene.add_gaussian_splats(name, centers=arrays.centers, covariances=arrays.covariances,
                                                     rgbs=arrays.rgbs, opacities=arrays.opacities, visible=visible)

    def _build_scene(self) -> None:
        scene = self.server.scene
        self._nodes["background"] = self._splats("/background", self.background)
        for index, o in enumerate(self.live.env.objects):
            placement0 = self.live.placements0[index]
            self._nodes[f"object {o.id}"] = scene.add_frame(f"/objects/{o.id}", show_axes=False)
            self._add_object_splats(o.id)
            entry = self.entries.get(o.id)
            colour = tuple(int(255 * c) for c in palette_colour(index))
            if entry is not None and entry.mesh and layout.resolve(self.out_dir, entry.mesh).is_file():
                vertices, faces = read_mesh(layout.resolve(self.out_dir, entry.mesh))
                self._nodes[f"mesh {o.id}"] = scene.add_mesh_simple(
                    f"/objects/{o.id}/mesh", placed_vertices(vertices, placement0), faces, color=MESH_COLOUR,
                    visible=False)
            parts = [read_mesh(layout.resolve(self.out_dir, path)) for path in (entry.collision if entry else ())]
            parts = [(placed_vertices(vertices, placement0), faces) for vertices, faces in parts]
            for k, (vertices, faces) in enumerate(parts):
                self._nodes[f"part {o.id} {k}"] = scene.add_mesh_simple(
                    f"/objects/{o.id}/collision/part_{k:02d}", vertices, faces, color=colour,
                    opacity=COLLISION_OPACITY, flat_shading=True, visible=False)
            self._add_grab_handles(o.id, parts)
        for k, view in enumerate(self.views):
            frustum = scene.add_camera_frustum(f"/cameras/{k}", fov=view.fov, aspect=view.aspect,
                                               scale=self.config.frustum_scale, color=(40, 40, 40),
                                               thickness=FRUSTUM_LINE_PX, thickness_units="screen",
                                               wxyz=view.wxyz, position=view.position)
            frustum.on_click(lambda event, view=view: self._look_through(event.client, view))
            self._nodes[f"camera {k}"] = frustum
        if self.views:
            view = self.views[0]
            centre = np.mean([m[:3, 3] for m in self.live.placements0], axis=0) if len(self.live.placements0) else None
            distance = float(np.linalg.norm(centre - view.position)) if centre is not None else 1.0
            self.server.initial_camera.position = view.position
            self.server.initial_camera.look_at = view.look_at(distance)
            self.server.initial_camera.up = (0.0, 0.0, 1.0)
            self.server.initial_camera.fov = view.fov
        scene.on_click()(self._on_click)

    def _add_object_splats(self, object_id: int) -> None:
        """(Re)send one object's splat node (instance colours or its own)."""
        arrays = self.objects[object_id]
        if self._instance_colours:
            arrays = arrays.coloured(palette_colour(self.live.object_ids.index(object_id)))
        self._nodes[f"splats {object_id}"] = self._splats(f"/objects/{object_id}/splats", arrays)

    def _add_grab_handles(self, object_id: int, parts: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """What a drag grabs: the object's convex parts (placed at t = 0), shrunk by ``GRAB_SHRINK``
        towards their centre so their depth stays behind the object's own Gaussians, drawn at
        opacity 0 (viser's client picks meshes, not splats; a hidden mesh is not picked)."""
        if not parts:
            return
        centre = np.concatenate([vertices for vertices, _ in parts]).mean(0)
        for k, (vertices, faces) in enumerate(parts):
            handle = self.server.scene.add_mesh_simple(
                f"/objects/{object_id}/grab/part_{k:02d}", centre + GRAB_SHRINK * (vertices - centre), faces,
                opacity=0.0, cast_shadow=False, receive_shadow=False)
            handle.on_drag("left")(lambda event, object_id=object_id: self._on_drag(object_id, event))

    def _look_through(self, client, view) -> None:
        client.camera.fov = view.fov
        client.camera.position = view.position
        client.camera.wxyz = view.wxyz

    # --- interactions -------------------------------------------------------------------

    def _on_click(self, event) -> None:
        self.live.shoot(event.ray_origin, event.ray_direction, self._speed.value)

    def _on_drag(self, object_id: int, event) -> None:
        if event.phase == "start":
            self.live.grab(object_id, event.start_position)
        elif event.phase == "update":
            self.live.drag_to(object_id, event.end_position)
        else:
            self.live.release(object_id)

    # --- the panel ----------------------------------------------------------------------

    def _build_panel(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Simulation"):
            self._play = gui.add_button("Pause" if self.live.playing else "Play")
            self._play.on_click(lambda _: self._toggle_play())
            gui.add_button("Reset").on_click(lambda _: self._reset())
            self._speed = gui.add_slider("Shot speed (m/s)", min=0.1, max=5.0, step=0.1,
                                         initial_value=self.config.shot_speed)
            self._clock = gui.add_markdown(self._clock_text())
            gui.add_markdown("Click an object to shoot it along the view ray; drag it to push it.")
        with gui.add_folder("Show"):
            toggles = {"Collision parts": self._show_parts, "Completed meshes": self._show_meshes,
                       "Instance colours": self._show_instance_colours,
                       "Source capture (before)": self._show_source, "Background only": self._show_background_only}
            self.toggles = {}
            for label, action in toggles.items():
                box = gui.add_checkbox(label, initial_value=False)
                box.on_update(lambda _, box=box, action=action: action(box.value))
                self.toggles[label] = box
            cameras = gui.add_checkbox("Cameras", initial_value=True)
            cameras.on_update(lambda _: self._show_cameras(cameras.value))
            self.toggles["Cameras"] = cameras
        with gui.add_folder("Objects", expand_by_default=False):
            for object_id, entry in self.entries.items():
                with gui.add_folder(f"object {object_id}", expand_by_default=False):
                    gui.add_markdown(object_markdown(entry))

    def _clock_text(self) -> str:
        state = "playing" if self.live.playing else "paused"
        return f"t = {self.live.time:.2f} s ({state}; {len(self.live.shots)} shots)"

    def _toggle_play(self) -> None:
        self.live.playing = not self.live.playing
        self._play.label = "Pause" if self.live.playing else "Play"

    def _reset(self) -> None:
        self.live.reset()
        self._send_motions()

    def _show_cameras(self, visible: bool) -> None:
        for key, node in self._nodes.items():
            if key.startswith("camera "):
                node.visible = visible

    def _show_parts(self, visible: bool) -> None:
        for key, node in self._nodes.items():
            if key.startswith("part "):
                node.visible = visible

    def _show_meshes(self, visible: bool) -> None:
        for key, node in self._nodes.items():
            if key.startswith("mesh "):
                node.visible = visible

    def _show_instance_colours(self, on: bool) -> None:
        self._instance_colours = on
        for object_id in self.live.object_ids:
            self._add_object_splats(object_id)

    def _show_source(self, on: bool) -> None:
        if on and self._source is None:
            source = source_gaussians(self.out_dir, self.manifest)
            if source is None:  # the capture's PLY has moved since the conversion
                self.toggles["Source capture (before)"].disabled = True
                return
            self._source = splat_arrays(source.to_kernel())
            self._nodes["source"] = self._splats("/source", self._source, visible=False)
        if "source" in self._nodes:
            self._nodes["source"].visible = on
        self._nodes["background"].visible = not on
        only_background = self.toggles["Background only"].value
        for object_id in self.live.object_ids:
            self._nodes[f"object {object_id}"].visible = not on and not only_background

    def _show_background_only(self, on: bool) -> None:
        source = self.toggles["Source capture (before)"].value
        for object_id in self.live.object_ids:
            self._nodes[f"object {object_id}"].visible = not on and not source

    # --- the update thread --------------------------------------------------------------

    def _send_motions(self) -> None:
        with self.server.atomic():
            for object_id, wxyz, position in self.live.motions():
                node = self._nodes[f"object {object_id}"]
                node.wxyz, node.position = wxyz, position

    def _update_loop(self) -> None:
        period = 1.0 / self.config.frame_rate
        last = time.perf_counter()
        last_clock = 0.0
        while not self._stop.is_set():
            now = time.perf_counter()
            if self.live.advance(now - last) or self.live.grabs:
                self._send_motions()
            if now - last_clock >= STATUS_PERIOD:
                self._clock.content = self._clock_text()
                last_clock = now
            last = now
            self._stop.wait(max(0.0, period - (time.perf_counter() - now)))
