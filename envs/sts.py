"""Simulated see-through visuotactile sensor (STS, thesis ch. 4) on a flat pad geom of any scene.

Contact sensing comes from MuJoCo's contact forces (`mj_contactForce` on the pad's contacts), not
from MuJoCo's built-in `tactile` sensor: measured on this pad (docs/door_tactile.md, "Which contact
signal"), the tactile sensor's per-taxel depth is dominated by the touching object's shape within
the taxels' reach (a 1.8 cm sphere: 147 mm summed depth at 0.5 N, 231 mm at 5 N) and its slip
channel reads relative velocity only, so a static shear force reads zero; an STS sees shear as
marker displacement whether or not the contact slides. Contact forces give the wrench directly.

From the contacts, in the sensor frame (z = pad normal, pointing out of the pad):

* `contact_wrench`: the true wrench (Fx, Fy, Fz, tau_z) on the pad, Fz > 0 when pressed;
* `raw_wrench`: the unscaled F~ = (Fx, Fy, Fz, tau_z) a kinesthetic-teaching logger records:
  a fixed nonlinear gain per axis (unknown to users of the data) plus seeded Gaussian noise;
* `tactile_image`: the marker-dot grid on the membrane as the internal camera sees it with the LEDs
  on; a contact moves the markers (shear -> tangential displacement under the contact, normal
  pressure -> markers pushed apart around the contact centre, torsion -> rotation about it) and
  brightens the pressed gel;
* `visual_image`: the scene through the clear membrane (the sensor's camera, LEDs off).

The sensor's `mode` ("visual" or "tactile") picks which image `image` returns; an action
dimension switches it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import mujoco
import numpy as np

from shiftkit.envs.cameras import disable_costly_flags, scene_option

MODES = ("visual", "tactile")


@dataclass(frozen=True)
class MembraneModel:
    """How contact deforms the marker grid (membrane units: millimetres on the pad)."""

    size_mm: tuple[float, float] = (36.0, 30.0)
    """Membrane extent seen by the camera along sensor x (image columns) and y (image rows); larger
    than the 28 x 22 mm pad face so that a load at the pad's end still deforms markers all round."""
    grid: tuple[int, int] = (11, 9)
    """Markers along x and y."""
    spread_mm: float = 4.0
    """Gaussian radius of the deformation around a contact."""
    shear_mm_per_n: float = 0.25
    """Tangential marker displacement under a contact per newton of shear."""
    normal_mm_per_n: float = 0.12
    """Outward (spacing-increasing) marker displacement per newton of normal force."""
    torsion_rad_per_nm: float = 4.0
    """Marker rotation about the contact per Nm of torsion."""
    saturation_mm: float = 3.0
    """Displacements saturate smoothly at this size (the gel's limited travel)."""


@dataclass(frozen=True)
class RawGain:
    """Fixed nonlinear gain from the true wrench to the unscaled F~: sign(F) k |F|^p + offset + noise."""

    scale: tuple[float, float, float, float] = (0.83, 0.79, 1.37, 41.0)
    power: tuple[float, float, float, float] = (0.9, 0.9, 0.8, 0.95)
    offset: tuple[float, float, float, float] = (0.02, -0.03, 0.11, 0.004)
    noise: tuple[float, float, float, float] = (0.05, 0.05, 0.08, 0.01)


def pad_contacts(model: mujoco.MjModel, data: mujoco.MjData, pad_geom: int) -> tuple[np.ndarray, ...]:
    """The pad's contacts in the world frame: positions (N, 3), forces on the pad (N, 3), torsional
    moments on the pad (N, 3, along each contact normal)."""
    n = data.ncon
    geoms = data.contact.geom[:n]
    idx = np.flatnonzero((geoms[:, 0] == pad_geom) | (geoms[:, 1] == pad_geom))
    pos, force, torsion = np.zeros((idx.size, 3)), np.zeros((idx.size, 3)), np.zeros((idx.size, 3))
    f6 = np.zeros(6)
    for row, i in enumerate(idx.tolist()):
        mujoco.mj_contactForce(model, data, i, f6)
        frame = data.contact.frame[i].reshape(3, 3)
        sign = -1.0 if geoms[i, 0] == pad_geom else 1.0  # the contact force acts on geom2 along +normal
        pos[row] = data.contact.pos[i]
        force[row] = sign * (f6[:3] @ frame)
        torsion[row] = sign * f6[3] * frame[0]
    return pos, force, torsion


@dataclass
class PadContacts:
    """The pad's contacts in the sensor frame: xy positions (m), forces on the pad (N, Fz > 0 pressed)
    and torsion about the pad normal (Nm)."""

    xy: np.ndarray
    force: np.ndarray
    torsion: np.ndarray

    def wrench(self) -> np.ndarray:
        """(Fx, Fy, Fz, tau_z) about the sensor origin."""
        if not len(self.xy):
            return np.zeros(4)
        f = self.force
        tau = np.sum(self.xy[:, 0] * f[:, 1] - self.xy[:, 1] * f[:, 0]) + self.torsion.sum()
        return np.array([*f.sum(axis=0), tau])


class STSSensor:
    """A simulated STS on `pad_geom`, its frame the site `site` (z out of the pad), its visual-mode
    camera `camera`. Images are `height` x `width` RGB (the membrane view fitted inside); noise
    comes from the seed given to `reset`."""

    def __init__(
        self,
        model: mujoco.MjModel,
        pad_geom: int,
        site: int,
        camera: str,
        width: int = 64,
        height: int = 64,
        membrane: MembraneModel | None = None,
        gain: RawGain | None = None,
    ) -> None:
        self.model, self.pad_geom, self.site, self.camera = model, pad_geom, site, camera
        self.width, self.height = width, height
        self.membrane = membrane or MembraneModel()
        self.gain = gain or RawGain()
        self.mode = "tactile"
        mem = self.membrane
        gx = (np.arange(mem.grid[0]) + 0.5) / mem.grid[0] - 0.5
        gy = (np.arange(mem.grid[1]) + 0.5) / mem.grid[1] - 0.5
        xx, yy = np.meshgrid(gx * mem.size_mm[0], gy * mem.size_mm[1])
        self.reference_mm = np.column_stack([xx.ravel(), yy.ravel()])
        self.px_per_mm = min(width / mem.size_mm[0], height / mem.size_mm[1])
        self._renderer: mujoco.Renderer | None = None
        self._rng = np.random.default_rng(0)
        # see-through: the clear gel and the robot itself are not in the view, only the scene
        self._option = scene_option("fast")
        self._option.geomgroup[3] = 0

    def reset(self, seed: int, mode: str = "tactile") -> None:
        """Restart the noise stream from `seed` and set the mode."""
        self._rng = np.random.default_rng(seed)
        self.set_mode(mode)

    def set_mode(self, mode: str) -> None:
        """Switch to "tactile" or "visual" (ValueError otherwise)."""
        if mode not in MODES:
            raise ValueError(f"STS mode must be one of {MODES}, got {mode!r}")
        self.mode = mode

    # ----------------------------------------------------------------- contact
    def contacts(self, data: mujoco.MjData) -> PadContacts:
        """The pad's contacts now, in the sensor frame."""
        pos, force, torsion = pad_contacts(self.model, data, self.pad_geom)
        rot = data.site_xmat[self.site].reshape(3, 3)
        local_f = force @ rot
        local_f[:, 2] *= -1.0  # pressing into the pad (against its outward normal) counts positive
        xy = ((pos - data.site_xpos[self.site]) @ rot)[:, :2]
        return PadContacts(xy=xy, force=local_f, torsion=torsion @ rot[:, 2])

    def contact_wrench(self, data: mujoco.MjData) -> np.ndarray:
        """The true contact wrench (Fx, Fy, Fz, tau_z) about the sensor origin (N, Nm)."""
        return self.contacts(data).wrench()

    def raw_wrench(self, wrench: np.ndarray) -> np.ndarray:
        """Unscaled F~ from a true wrench (consumes the sensor's noise stream)."""
        g = self.gain
        w = np.asarray(wrench, dtype=np.float64)
        out = np.sign(w) * np.asarray(g.scale) * np.abs(w) ** np.asarray(g.power) + np.asarray(g.offset)
        return out + self._rng.normal(0.0, g.noise)

    # ----------------------------------------------------------------- images
    def marker_positions(self, contacts: PadContacts) -> np.ndarray:
        """(M, 2) marker positions (mm, membrane frame) deformed by the contacts."""
        mem = self.membrane
        ref = self.reference_mm
        disp = np.zeros_like(ref)
        for xy, f, tz in zip(contacts.xy * 1000.0, contacts.force, contacts.torsion, strict=True):
            r = ref - xy
            w = np.exp(-np.sum(r * r, axis=1) / (2 * mem.spread_mm**2))[:, None]
            disp += w * (
                mem.shear_mm_per_n * f[:2] + mem.torsion_rad_per_nm * tz * np.column_stack([-r[:, 1], r[:, 0]])
            )
        # the gel spreads the normal load of all points into one pressure patch around the centre of
        # pressure, which pushes the markers apart
        normal = np.clip(contacts.force[:, 2], 0.0, None) if len(contacts.xy) else np.zeros(0)
        if normal.sum() > 1e-9:
            xy = contacts.xy * 1000.0
            centre = (normal[:, None] * xy).sum(axis=0) / normal.sum()
            r = ref - centre
            w = np.exp(-np.sum(r * r, axis=1) / (2 * mem.spread_mm**2))[:, None]
            disp += w * mem.normal_mm_per_n * normal.sum() * r / mem.spread_mm
        size = np.linalg.norm(disp, axis=1, keepdims=True)
        scale = np.where(
            size > 1e-12, mem.saturation_mm * np.tanh(size / mem.saturation_mm) / np.maximum(size, 1e-12), 1
        )
        return ref + disp * scale

    def tactile_image(self, data: mujoco.MjData) -> np.ndarray:
        """Marker image of the current contacts (noise from the sensor's stream)."""
        contacts = self.contacts(data)
        return self.render_markers(self.marker_positions(contacts), contacts)

    def render_markers(self, markers_mm: np.ndarray, contacts: PadContacts) -> np.ndarray:
        """The tactile image (H, W, 3) uint8: markers at `markers_mm` (membrane mm) over the contacts'
        glow, with noise."""
        mem = self.membrane
        img = np.full((self.height, self.width), 200.0)
        # pressed gel scatters more LED light: a soft bright blob around each contact
        yy, xx = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        for xy, f in zip(contacts.xy * 1000.0, contacts.force, strict=True):
            cx, cy = self._to_px(xy)
            sigma = mem.spread_mm * self.px_per_mm
            img += min(40.0, 3.0 * max(0.0, f[2])) * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma**2))
        canvas = np.clip(img, 0, 255).astype(np.uint8)
        shift = 4  # sub-pixel marker centres
        radius = int(round(1.6 * self.px_per_mm * (1 << shift) * 0.5))
        for p in markers_mm:
            cx, cy = self._to_px(p)
            centre = (int(round(cx * (1 << shift))), int(round(cy * (1 << shift))))
            cv2.circle(canvas, centre, radius, 25, -1, cv2.LINE_AA, shift)
        noisy = canvas.astype(np.float64) + self._rng.normal(0.0, 3.0, canvas.shape)
        gray = np.clip(noisy, 0, 255).astype(np.uint8)
        # a slightly warm tint like the LED-lit membrane
        return np.stack([gray, (gray * 0.95).astype(np.uint8), (gray * 0.85).astype(np.uint8)], axis=-1)

    def _to_px(self, mm: np.ndarray) -> tuple[float, float]:
        """Membrane mm -> image pixel coordinates (x along columns, y along rows, centred)."""
        return (self.width - 1) / 2 + mm[0] * self.px_per_mm, (self.height - 1) / 2 + mm[1] * self.px_per_mm

    def visual_image(self, data: mujoco.MjData) -> np.ndarray:
        """The visual-mode image (H, W, 3) uint8: the scene through the clear gel."""
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, height=self.height, width=self.width)
        self._renderer.update_scene(data, camera=self.camera, scene_option=self._option)
        disable_costly_flags(self._renderer.scene)
        return self._renderer.render().copy()

    def image(self, data: mujoco.MjData) -> np.ndarray:
        """The image of the active mode."""
        return self.tactile_image(data) if self.mode == "tactile" else self.visual_image(data)

    def close(self) -> None:
        """Free the visual-mode renderer."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
