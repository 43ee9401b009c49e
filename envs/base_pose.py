"""Mobile-base poses for multiview manipulation (thesis §3.5, docs/multiview.md).

A base pose is an SE(2) pose (x, y, yaw) of the robot base in the world. The base carries a rigidly
mounted camera; a pose is *aimed* when the camera's optical axis passes through a chosen task centre
at a given distance. Since the camera is fixed to the base, an aimed pose puts the task centre at one
fixed point of the base frame, the aim point `camera_position + distance * camera_axis`: for a
sampled yaw the base x, y follow in closed form. Small uniform noise is then added (the reference
code: +-2 cm, +-0.02 rad), which keeps the objects in view while varying the exact viewpoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class BasePose:
    """SE(2) pose of the robot base in the world frame."""

    x: float
    y: float
    yaw: float

    def rotation(self) -> np.ndarray:
        """(3, 3) rotation base -> world."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    def to_world(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) from the base frame into the world frame."""
        return np.asarray(points) @ self.rotation().T + [self.x, self.y, 0.0]

    def to_base(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) from the world frame into the base frame."""
        return (np.asarray(points) - [self.x, self.y, 0.0]) @ self.rotation()

    def as_dict(self) -> dict[str, float]:
        """The camera-metadata form `{"x", "y", "yaw"}`."""
        return {"x": float(self.x), "y": float(self.y), "yaw": float(self.yaw)}

    @classmethod
    def from_dict(cls, d: dict[str, float]) -> BasePose:
        """The pose in its camera-metadata form `{"x", "y", "yaw"}` (`to_dict`'s inverse)."""
        return cls(float(d["x"]), float(d["y"]), float(d["yaw"]))


@dataclass(frozen=True)
class BasePoseSampler:
    """Samples aimed base poses: yaw ~ U(yaw_range), x, y solved, then uniform noise."""

    centre: tuple[float, float, float]
    """Task centre in the world frame."""
    camera_position: tuple[float, float, float]
    """Camera origin in the base frame."""
    camera_axis: tuple[float, float, float]
    """Optical axis (viewing direction) in the base frame; normalised here."""
    distance: float
    """Distance from the camera to the task centre along the optical axis (metres)."""
    yaw_range: tuple[float, float]
    """Base yaw interval (rad) sampled uniformly (45 deg wide in simulation)."""
    xy_noise: float = 0.02
    """Half-width of the uniform noise on base x and y (metres)."""
    yaw_noise: float = 0.02
    """Half-width of the uniform noise on base yaw (rad)."""
    height_tolerance: float = 0.01
    """Largest accepted gap between the aim point's height and the centre's (the base moves in the
    plane only, so the camera height and tilt must reach the centre at `distance`)."""

    def __post_init__(self) -> None:
        if not self.distance > 0 or not self.yaw_range[0] <= self.yaw_range[1]:
            raise ValueError(f"need distance > 0 and yaw_range low <= high, got {self.distance}, {self.yaw_range}")
        if self.xy_noise < 0 or self.yaw_noise < 0:
            raise ValueError("noise half-widths must be >= 0")
        gap = abs(self.aim_point()[2] - self.centre[2])
        if gap > self.height_tolerance:
            raise ValueError(
                f"the optical axis is {gap:.3f} m above/below the centre at distance {self.distance}: "
                "change the distance or the camera tilt"
            )

    def aim_point(self) -> np.ndarray:
        """Where the task centre sits in the base frame for every aimed pose."""
        axis = np.asarray(self.camera_axis, dtype=np.float64)
        return np.asarray(self.camera_position, dtype=np.float64) + self.distance * axis / np.linalg.norm(axis)

    def solve(self, yaw: float) -> BasePose:
        """The aimed base pose with this yaw (no noise)."""
        aim = self.aim_point()
        c, s = np.cos(yaw), np.sin(yaw)
        x = self.centre[0] - (c * aim[0] - s * aim[1])
        y = self.centre[1] - (s * aim[0] + c * aim[1])
        return BasePose(float(x), float(y), float(yaw))

    def centre_pose(self) -> BasePose:
        """The fixed-view pose: the middle of the yaw range, no noise."""
        return self.solve(0.5 * (self.yaw_range[0] + self.yaw_range[1]))

    def sample(self, rng: np.random.Generator) -> BasePose:
        """One noisy aimed pose; every random number comes from `rng`."""
        pose = self.solve(rng.uniform(*self.yaw_range))
        dx, dy = rng.uniform(-self.xy_noise, self.xy_noise, 2)
        dyaw = rng.uniform(-self.yaw_noise, self.yaw_noise)
        return BasePose(pose.x + float(dx), pose.y + float(dy), pose.yaw + float(dyaw))

    def sample_at(self, yaw: float, rng: np.random.Generator) -> BasePose:
        """An aimed pose at exactly this yaw (any, also outside `yaw_range`) with x, y noise only
        (evaluation sweeps over yaw bins)."""
        pose = self.solve(yaw)
        dx, dy = rng.uniform(-self.xy_noise, self.xy_noise, 2)
        return BasePose(pose.x + float(dx), pose.y + float(dy), pose.yaw)

    def axis_miss(self, pose: BasePose) -> float:
        """Distance (metres) between the task centre and the camera's optical axis at `pose`."""
        rot = pose.rotation()
        origin = pose.to_world(np.asarray(self.camera_position, dtype=np.float64))
        axis = rot @ np.asarray(self.camera_axis, dtype=np.float64)
        axis /= np.linalg.norm(axis)
        offset = np.asarray(self.centre, dtype=np.float64) - origin
        return float(np.linalg.norm(offset - (offset @ axis) * axis))

    def miss_bound(self) -> float:
        """Largest `axis_miss` the noise can cause: the aim point moves by at most the xy noise plus
        the yaw noise times its horizontal distance from the base origin, plus the height gap."""
        aim = self.aim_point()
        return float(
            np.hypot(self.xy_noise, self.xy_noise)
            + self.yaw_noise * np.hypot(aim[0], aim[1])
            + abs(aim[2] - self.centre[2])
        )


# The multiview rig (thesis ch. 3; docs/multiview.md): where the base-mounted camera sits and the
# base poses sampled. The scene (`envs/multiview/physics.py`) is built around it; it lives here so that
# the multiview stage's defaults load without the scene and MuJoCo.
TABLE_Z = 0.125
AIM = np.array([0.0, 0.5, TABLE_Z])  # the task centre's place in the base frame
CAMERA_NAME = "base"
CAMERA_POS = np.array([0.3, -0.05, 0.6])
YAW_RANGE = (-0.6, 0.2)  # 45.8 deg, the reference's simulated range (docs/multiview.md)
WORLD_CENTRE = (0.0, 0.0, TABLE_Z)
SAMPLER = BasePoseSampler(
    centre=WORLD_CENTRE,
    camera_position=tuple(CAMERA_POS),
    camera_axis=tuple(AIM - CAMERA_POS),
    distance=float(np.linalg.norm(AIM - CAMERA_POS)),
    yaw_range=YAW_RANGE,
)
