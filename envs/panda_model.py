"""The Franka Panda robot model shipped by gymnasium-robotics (kitchen_franka, MIT), for every scene.

Its `assets.xml` sets `meshdir="franka_assets/meshes"` relative to the including model file, so a
scene composed elsewhere resolves the mesh files itself: `panda_spec` returns an `MjSpec` of the arm
(7 joints + 2 fingers, position actuators) with absolute mesh paths, ready for a scene to add to.
"""

from __future__ import annotations

import importlib.util
import os

import mujoco


def franka_assets_dir() -> str:
    """The Franka Panda MJCF folder shipped by gymnasium-robotics (found without importing it)."""
    spec = importlib.util.find_spec("gymnasium_robotics")
    if spec is None or spec.origin is None:
        raise ImportError("gymnasium-robotics is required for the Panda model")
    return os.path.join(os.path.dirname(spec.origin), "envs", "assets", "kitchen_franka", "franka_assets")


def panda_spec(model_name: str, timestep: float = 0.002, impratio: float = 10.0) -> mujoco.MjSpec:
    """An `MjSpec` named `model_name` holding the Panda arm (bodies `panda0_*`, joints
    `robot:panda0_joint1..7`, fingers `robot:panda0_finger_joint1/2`) at the world origin, with the
    physics every scene here uses (implicit-fast integration, elliptic friction cones; `impratio`
    stiffens friction so held objects do not creep) and a 640x480 offscreen buffer."""
    root = franka_assets_dir()
    xml = (
        f'<mujoco model="{model_name}"><include file="{root}/assets.xml"/>'
        f'<include file="{root}/actuator.xml"/><worldbody><include file="{root}/chain.xml"/></worldbody></mujoco>'
    )
    spec = mujoco.MjSpec.from_string(xml)
    spec.meshdir = ""
    for mesh in spec.meshes:  # the include resolved them beside franka_assets/, not in meshes/
        mesh.file = os.path.join(root, "meshes", os.path.relpath(mesh.file, root))
    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = impratio
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480
    return spec
