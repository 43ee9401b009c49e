"""Cameras shared by the scenes: placement, offscreen RGB-D rendering, intrinsics and extrinsics.

Dataset renderers switch off shadows, reflections and the skybox (on CPU rendering through Mesa
they cost most of the frame time). `quality="fast"` shows the low-poly collision geometry (geom
group 3) instead of the visual meshes (group 0); scene geoms (group 1) are shown in both modes.
Set `MUJOCO_GL=egl` before importing mujoco for headless use.
"""

from __future__ import annotations

import mujoco
import numpy as np

QUALITIES = ("fast", "full")


def look_at(pos, target) -> tuple[float, ...]:
    """`xyaxes` of a camera at `pos` looking at `target` with world z up."""
    fwd = np.asarray(target, float) - np.asarray(pos, float)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    return (*right, *up)


def scene_option(quality: str) -> mujoco.MjvOption:
    """MuJoCo visual options for a render quality: "fast" shows the collision geoms, "full" the visual
    meshes (ValueError otherwise)."""
    if quality not in QUALITIES:
        raise ValueError(f"render quality must be one of {QUALITIES}, got {quality!r}")
    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 0
    opt.geomgroup[1] = 1
    opt.geomgroup[3 if quality == "fast" else 0] = 1
    return opt


def disable_costly_flags(scene: mujoco.MjvScene) -> None:
    """Shadows, reflections and skybox off (the dataset-renderer setting)."""
    scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    scene.flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0


class CameraRenderer:
    """Renders named cameras of a model to RGB (H, W, 3) uint8 and depth (H, W) float32 metres."""

    def __init__(self, model: mujoco.MjModel, width: int = 64, height: int = 48, quality: str = "fast") -> None:
        self.width, self.height = width, height
        self._option = scene_option(quality)
        self._renderer = mujoco.Renderer(model, height=height, width=width)
        disable_costly_flags(self._renderer.scene)
        self._depth: mujoco.Renderer | None = None
        self._model = model

    def rgb(self, data: mujoco.MjData, camera: str) -> np.ndarray:
        """(H, W, 3) uint8 RGB image from `camera`."""
        self._renderer.update_scene(data, camera=camera, scene_option=self._option)
        disable_costly_flags(self._renderer.scene)
        return self._renderer.render()

    def depth(self, data: mujoco.MjData, camera: str) -> np.ndarray:
        """(H, W) float32 depth image (m) from `camera`; the depth renderer is built on first use."""
        if self._depth is None:
            self._depth = mujoco.Renderer(self._model, height=self.height, width=self.width)
            self._depth.enable_depth_rendering()
        self._depth.update_scene(data, camera=camera, scene_option=self._option)
        return self._depth.render().astype(np.float32)

    def close(self) -> None:
        """Free the renderers."""
        self._renderer.close()
        if self._depth is not None:
            self._depth.close()


def camera_intrinsics(model: mujoco.MjModel, camera: str, width: int, height: int) -> dict[str, float]:
    """Pinhole intrinsics (pixels) of a MuJoCo camera rendered at width x height (square pixels)."""
    fovy = np.deg2rad(model.cam(camera).fovy[0])
    f = 0.5 * height / np.tan(fovy / 2)
    return {
        "fx": float(f),
        "fy": float(f),
        "cx": (width - 1) / 2,
        "cy": (height - 1) / 2,
        "width": width,
        "height": height,
    }


def camera_extrinsics(model: mujoco.MjModel, data: mujoco.MjData, camera: str) -> dict[str, list[float]]:
    """Camera pose in the base/world frame: position and rotation matrix (MuJoCo camera axes: x right,
    y up, looking along -z)."""
    cam = model.cam(camera).id
    return {"position": data.cam_xpos[cam].tolist(), "rotation": data.cam_xmat[cam].reshape(3, 3).tolist()}


class SceneRendering:
    """Rendering for a scene's gymnasium env (mixed in before `gym.Env`): the env provides
    `physics.model` / `physics.data`, `camera` (the default), `width`, `height`, `render_quality` and
    `render_mode`; one `CameraRenderer`, built on first use, serves every camera."""

    _renderer: CameraRenderer | None = None

    def _get_renderer(self) -> CameraRenderer:
        if self._renderer is None:
            self._renderer = CameraRenderer(self.physics.model, self.width, self.height, self.render_quality)
        return self._renderer

    def render_rgb(self, camera: str | None = None) -> np.ndarray:
        """(H, W, 3) uint8 RGB image from `camera` (default: the env's camera)."""
        return self._get_renderer().rgb(self.physics.data, camera or self.camera)

    def render_depth(self, camera: str | None = None) -> np.ndarray:
        """(H, W) float32 depth image (m) from `camera` (default: the env's camera)."""
        return self._get_renderer().depth(self.physics.data, camera or self.camera)

    def render(self):
        """The default camera's image for `render_mode`: depth for "depth_array", else RGB."""
        return self.render_depth() if self.render_mode == "depth_array" else self.render_rgb()

    def close(self) -> None:
        """Free the renderer (a later render builds a new one)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
