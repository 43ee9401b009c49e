"""Scene pieces every environment family composes with `mujoco.MjSpec`: boxes, the light and the
ground plane. Geom groups: robot visual meshes 0, scene 1, robot collision 3 (the fast render mode
of `cameras` shows 1 and 3)."""

from __future__ import annotations

from collections.abc import Sequence

import mujoco

SCENE_GROUP = 1


def add_box(body, name: str, half, pos, rgba, group: int = SCENE_GROUP, collide: bool = True, quat=None):
    """A box geom `name` on `body` (half sizes, position and optional wxyz quaternion in the body frame)."""
    g = body.add_geom()
    g.name = name
    g.type = mujoco.mjtGeom.mjGEOM_BOX
    g.size = list(half)
    g.pos = list(pos)
    if quat is not None:
        g.quat = list(quat)
    g.rgba = list(rgba)
    g.group = group
    g.contype = g.conaffinity = 1 if collide else 0
    return g


def add_light_and_ground(
    world, light_pos: Sequence[float], light_dir: Sequence[float], ground_half: float = 2.0
) -> None:
    """A shadowless directional-ish light (shadows cost most of a CPU render) and a visual-only
    grey ground plane named "ground"."""
    light = world.add_light()
    light.pos = list(light_pos)
    light.dir = list(light_dir)
    light.diffuse = [0.8, 0.8, 0.8]
    light.castshadow = False
    floor = world.add_geom()
    floor.name = "ground"
    floor.type = mujoco.mjtGeom.mjGEOM_PLANE
    floor.size = [ground_half, ground_half, 0.1]
    floor.rgba = [0.35, 0.35, 0.38, 1.0]
    floor.group = SCENE_GROUP
    floor.contype = floor.conaffinity = 0
