"""``phirie view SCENE`` on a capture before conversion: point at the objects to convert.

The browser shows the capture's Gaussians (in the capture's own frame, the cameras' level vote
as up) and its camera frustums. A click on an object adds a prompt (``observe.prompts``):

1. ``PromptPicker.hit``: the click's ray meets the first opaque Gaussian along it (its centre
   within 2 standard deviations, or a small angle, of the ray);
2. ``PromptPicker.photo_point``: of the cameras that see that point — in front of them, inside
   the photo, no opaque Gaussian on the line of sight before it — the one whose line of sight
   is closest to the click's own direction (the photo most like the view) takes it; the point's
   pixel there makes an ``IMAGE:U,V`` prompt, with the panel's label.

The prompts are saved in ``SCENE/prompts.json`` as they are added (``update_prompts``: written
to a temporary name and renamed; the file's own prompts and keys are kept, one it cannot read
is left alone and the panel says why). This is the one file the viewer writes in a scene
folder, and only on a click. ``phirie convert SCENE`` then reads it. The picker needs no viser
(tested alone); ``CaptureViewer`` serves it.
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path

import numpy as np

from phirie_jax.errors import SceneInputError
from phirie_jax.observe.masks import camera_problem
from phirie_jax.observe.prompts import PROMPTS_FILE, Prompt, read_prompts_file, update_prompts
from phirie_jax.types import Camera, GaussianSplatData

PICK_OPACITY = 0.5      # a click stops at Gaussians at least this opaque
PICK_SIGMAS = 2.0       # ... whose centre lies within this many standard deviations of the ray
PICK_ANGLE = 0.004      # ... or within this angle (radians) of it, for the smallest ones
OCCLUDED_BEFORE = 0.97  # an opaque Gaussian on the line of sight before this fraction of the depth hides the point
EDGE_PX = 2.0           # a photo point this close to the border is not taken
MARKER_COLOUR = (255, 60, 60)


@dataclasses.dataclass(frozen=True)
class PhotoPoint:
    view: int
    image: str
    u: float
    v: float


class PromptPicker:
    """Clicks on a capture's Gaussians → ``IMAGE:U,V`` prompts (module docstring). Pure NumPy."""

    def __init__(self, gaussians: GaussianSplatData, cameras: tuple[Camera, ...]):
        opacity = 1.0 / (1.0 + np.exp(-gaussians.opacity_logits.astype(np.float64)))
        keep = opacity >= PICK_OPACITY
        self.points = gaussians.means[keep].astype(np.float64)                   # (M, 3)
        self.radii = PICK_SIGMAS * np.exp(gaussians.log_scales[keep].astype(np.float64).max(1))  # (M,)
        self.cameras = cameras

    def _along(self, origin: np.ndarray, direction: np.ndarray, limit: float | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
        """(indices, distances along the ray) of the opaque Gaussians the ray (unit ``direction``)
        passes within reach of, in front of ``origin`` (and before ``limit``)."""
        offset = self.points - origin
        t = offset @ direction
        ahead = t > 0 if limit is None else (t > 0) & (t < limit)
        idx = np.flatnonzero(ahead)
        miss = np.linalg.norm(offset[idx] - t[idx, None] * direction, axis=1)
        near = miss <= np.maximum(self.radii[idx], PICK_ANGLE * t[idx])
        return idx[near], t[idx[near]]

    def hit(self, origin, direction) -> np.ndarray | None:
        """(3,) where the ray first meets an opaque Gaussian, or None."""
        origin, direction = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
        direction = direction / np.linalg.norm(direction)
        idx, t = self._along(origin, direction)
        if len(idx) == 0:
            return None
        first = int(np.argmin(t))
        return origin + t[first] * direction

    def photo_point(self, point: np.ndarray, direction) -> PhotoPoint | None:
        """The photo that shows ``point`` most as the click's ray (``direction``) saw it, and the
        point's pixel there (image-viewer coordinates); None when no camera sees it."""
        direction = np.asarray(direction, np.float64) / np.linalg.norm(direction)
        ranked = []
        for k, cam in enumerate(self.cameras):
            if camera_problem(cam) is not None:
                continue
            uv, depth = cam.project(point[None])
            u, v = uv[0]
            if not (depth[0] > 0 and EDGE_PX <= u < cam.width - EDGE_PX and EDGE_PX <= v < cam.height - EDGE_PX):
                continue
            sight = point - cam.center
            ranked.append((-float(sight @ direction) / np.linalg.norm(sight), k, float(u), float(v)))
        for _, k, u, v in sorted(ranked):
            cam = self.cameras[k]
            sight = point - cam.center
            length = float(np.linalg.norm(sight))
            idx, _ = self._along(cam.center, sight / length, OCCLUDED_BEFORE * length)
            if len(idx) == 0:
                return PhotoPoint(k, cam.name, round(u, 1), round(v, 1))
        return None

    def prompt_at(self, origin, direction, label: str | None = None) -> tuple[Prompt | None, str]:
        """(the prompt a click makes, or None, and what happened, for the panel)."""
        point = self.hit(origin, direction)
        if point is None:
            return None, "the click met no opaque Gaussian"
        found = self.photo_point(point, direction)
        if found is None:
            return None, "no photo shows the clicked point unhidden"
        prompt = Prompt(found.image, point=(found.u, found.v), label=label or None)
        return prompt, f"{prompt.as_text()} (the point seen in photo {found.image})"


class CaptureViewer:
    """The viewer of a capture folder, serving until ``close`` (module docstring)."""

    def __init__(self, scene_dir: str | Path, config):
        from phirie_jax.frame.estimate import cameras_up
        from phirie_jax.io.scene import load_scene
        from phirie_jax.view.scene import camera_view, splat_arrays
        from phirie_jax.view.server import FRUSTUM_LINE_PX, _viser

        viser = _viser()
        self.scene = load_scene(scene_dir)
        self.path = self.scene.root / PROMPTS_FILE
        cameras = self.scene.require_cameras()
        gaussians = self.scene.require_gaussians()
        self.picker = PromptPicker(gaussians, cameras)
        self.prompts: list[Prompt] = read_prompts_file(self.path) if self.path.is_file() else []
        self.added: list[Prompt] = []                  # this session's, in order (what Undo takes back)
        self._lock = threading.Lock()
        self.server = viser.ViserServer(host=config.host, port=config.port, verbose=False)
        self.server.gui.configure_theme(control_width="medium", show_share_button=False)
        up = cameras_up(cameras)
        self.server.scene.set_up_direction(tuple(float(v) for v in up))
        arrays = splat_arrays(gaussians.to_kernel())
        self.server.scene.add_gaussian_splats("/capture", centers=arrays.centers, covariances=arrays.covariances,
                                              rgbs=arrays.rgbs, opacities=arrays.opacities)
        views = [camera_view(c) for c in cameras]
        extent = float(np.linalg.norm(np.ptp([v.position for v in views], axis=0))) or 1.0
        self._marker_radius = 0.005 * extent
        for k, view in enumerate(views):
            self.server.scene.add_camera_frustum(f"/cameras/{k}", fov=view.fov, aspect=view.aspect,
                                                 scale=0.03 * extent, color=(40, 40, 40), thickness=FRUSTUM_LINE_PX,
                                                 thickness_units="screen", wxyz=view.wxyz, position=view.position)
        if views:
            self.server.initial_camera.position = views[0].position
            self.server.initial_camera.look_at = views[0].look_at(0.5 * extent)
            self.server.initial_camera.up = tuple(float(v) for v in up)
            self.server.initial_camera.fov = views[0].fov
        gui = self.server.gui
        with gui.add_folder("Prompts"):
            gui.add_markdown(f"Click an object to convert: each click adds a prompt to `{self.path}`, "
                             "which `phirie convert` reads.")
            self._label = gui.add_text("Label of the next object", initial_value="")
            gui.add_button("Undo my last prompt").on_click(lambda _: self.undo())
            self._status = gui.add_markdown("")
            self._list = gui.add_markdown("")
        self._markers: list = []
        self._show()
        self.server.scene.on_click()(lambda event: self.click(event.ray_origin, event.ray_direction))

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"

    def close(self) -> None:
        self.server.stop()

    def click(self, origin, direction) -> Prompt | None:
        """Add the prompt a click makes (saved at once); returns it, or None (the panel says why)."""
        with self._lock:
            prompt, said = self.picker.prompt_at(origin, direction, self._label.value.strip() or None)
            if prompt is not None:
                try:
                    self.prompts = update_prompts(self.path, add=[prompt])
                except (SceneInputError, OSError) as err:
                    self._status.content = f"**not saved**: {err}"
                    return None
                self.added.append(prompt)
                hit = self.picker.hit(origin, direction)
                self._markers.append(self.server.scene.add_icosphere(
                    f"/prompts/{len(self.added)}", radius=self._marker_radius, color=MARKER_COLOUR, position=hit))
            self._status.content = ("added " if prompt else "no prompt: ") + said
            self._show()
            return prompt

    def undo(self) -> None:
        """Take back this session's last prompt (the file's other prompts stay)."""
        with self._lock:
            if not self.added:
                self._status.content = "nothing of this session to undo"
                return
            last = self.added.pop()
            try:
                self.prompts = update_prompts(self.path, remove=[last])
            except (SceneInputError, OSError) as err:
                self.added.append(last)
                self._status.content = f"**not saved**: {err}"
                return
            if self._markers:
                self._markers.pop().remove()
            self._status.content = f"removed {last.as_text()}"
            self._show()

    def _show(self) -> None:
        lines = [f"{k}. `{p.as_text()}`" for k, p in enumerate(self.prompts, start=1)]
        self._list.content = "\n".join(lines) if lines else "no prompts yet"
