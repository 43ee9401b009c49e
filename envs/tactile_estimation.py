"""Tactile wrench estimation from STS marker images with OpenCV (thesis §4.3.3).

Per frame: adaptive threshold of the grey image, marker centroids (connected components of
plausible size), each marker of the reference (no-contact) frame tracked to the nearest centroid of
its position in the previous frame (so displacements may exceed the marker spacing),
outliers rejected from nearest-neighbour statistics (a marker whose displacement differs from its
neighbours' median by far more than their spread), then, in pixels (unscaled):

* Fx, Fy = mean marker displacement;
* Fz = mean surface depth, inferred from the local change of marker spacing (pressure pushes the
  markers apart around the contact: the summed increase, beyond a noise deadband, of each marker's
  mean distance to its reference neighbours);
* tau_z = mean displacement tangential about the centre of maximal normal force (the marker whose
  spacing grew most), over the markers around it.

The estimate is low-pass filtered over frames (first-order, `smoothing`).
"""

from __future__ import annotations

import cv2
import numpy as np


def detect_markers(image: np.ndarray, min_area: int = 3, max_area: int = 80) -> np.ndarray:
    """(N, 2) marker centroids (x = column, y = row, pixels) of a dark-dot marker image."""
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    binary = cv2.adaptiveThreshold(gray, 255, cv2.ADAPTIVE_THRESH_GAUSSIAN_C, cv2.THRESH_BINARY_INV, 11, 20)
    count, _, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    area = stats[1:count, cv2.CC_STAT_AREA]
    keep = (area >= min_area) & (area <= max_area)
    return centroids[1:count][keep]


class MarkerWrenchEstimator:
    """Stateful estimator: `reset(reference_image)` per episode, then `update(image)` per frame."""

    def __init__(
        self,
        max_track_px: float = 3.0,
        neighbours: int = 4,
        smoothing: float = 0.5,
        spacing_deadband: float = 0.08,
        pressure_radius: float = 1.2,
    ) -> None:
        self.max_track_px, self.neighbours, self.smoothing = max_track_px, neighbours, smoothing
        self.spacing_deadband = spacing_deadband  # px: centroid noise is not pressure
        self.pressure_radius = pressure_radius  # in marker spacings: the pressure pattern's size
        self.reference = np.zeros((0, 2))
        self._ref_spacing = np.zeros(0)
        self._ref_nn = np.zeros((0, 0), dtype=np.int64)
        self._state: np.ndarray | None = None
        self._prev: np.ndarray | None = None

    def reset(self, reference_image: np.ndarray) -> None:
        """Start an episode: detect the markers of the undeformed `reference_image`."""
        self.reference = detect_markers(reference_image)
        d = _distances(self.reference, self.reference)
        np.fill_diagonal(d, np.inf)
        k = min(self.neighbours, max(1, len(self.reference) - 1))
        self._ref_nn = np.argsort(d, axis=1)[:, :k]
        self._ref_spacing = np.take_along_axis(d, self._ref_nn, axis=1).mean(axis=1)
        self._state = None
        self._prev = None

    def raw(self, image: np.ndarray) -> np.ndarray:
        """Unfiltered (Fx, Fy, Fz, tau_z) of one frame, in pixels."""
        ref = self.reference
        if len(ref) < 3:
            return np.zeros(4)
        found = detect_markers(image)
        if not len(found):
            return np.zeros(4)
        # track from the previous frame (small motions at 10 Hz), identities from the reference
        prev = ref if self._prev is None else self._prev
        d = _distances(prev, found)
        nearest = d.argmin(axis=1)
        tracked = d[np.arange(len(ref)), nearest] <= self.max_track_px
        cur = np.where(tracked[:, None], found[nearest], prev)
        disp = cur - ref
        # outliers: displacement far from the median of the reference neighbours' displacements
        neigh = disp[self._ref_nn]
        med = np.median(neigh, axis=1)
        spread = np.median(np.linalg.norm(neigh - med[:, None], axis=2), axis=1)
        ok = tracked & (np.linalg.norm(disp - med, axis=1) <= 3.0 * spread + 1.0)
        if ok.sum() < 3:
            return np.zeros(4)
        disp = np.where(ok[:, None], disp, med)  # a rejected marker takes its neighbours' motion
        cur = ref + disp
        self._prev = cur
        spacing = np.linalg.norm(cur[:, None, :] - cur[self._ref_nn], axis=2).mean(axis=1)
        growth = spacing - self._ref_spacing
        pressed = np.clip(growth - self.spacing_deadband, 0.0, None)
        fz = float(pressed.sum())
        centre = cur[int(np.argmax(growth))]
        if fz > 0:
            centre = (pressed[:, None] * ref).sum(axis=0) / pressed.sum()
        r = ref - centre
        shear = disp
        if fz > 0:
            # pressure pushes markers apart about the centre; where the view cuts that pattern off its
            # mean is not zero, so the radial part fitted about the centre is removed before averaging
            sigma = self.pressure_radius * np.median(self._ref_spacing)
            radial = np.exp(-np.sum(r * r, axis=1) / (2 * sigma**2))[:, None] * r / sigma
            k = float(np.sum(radial * (disp - disp.mean(axis=0)))) / max(float(np.sum(radial * radial)), 1e-9)
            shear = disp - max(k, 0.0) * radial
        dist = np.linalg.norm(r, axis=1)
        near = (dist > 1e-6) & (dist < 3.0 * np.median(self._ref_spacing))
        tau = (
            float(np.mean((r[near, 0] * shear[near, 1] - r[near, 1] * shear[near, 0]) / dist[near]))
            if near.any()
            else 0.0
        )
        fx, fy = shear.mean(axis=0)
        return np.array([fx, fy, fz, tau])

    def update(self, image: np.ndarray) -> np.ndarray:
        """Low-pass filtered estimate after this frame."""
        raw = self.raw(image)
        self._state = raw if self._state is None else self.smoothing * self._state + (1 - self.smoothing) * raw
        return self._state.copy()


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
