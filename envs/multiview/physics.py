"""Multiview scene: a Panda on a mobile base, a base-mounted RGB-D camera, a table with task objects.

Physics only, no task logic (tasks live in `tasks`). The MuJoCo frame *is* the robot base frame:
the arm's root and the camera sit at fixed places in it, and the world (table, fixtures, door) is
one body, `task_frame`, placed at the inverse of the base pose at every reset. Free objects are
children of the MuJoCo world, so their `sim.qpos` is in the base frame too (`rebase_qpos` moves a
recorded state to another base pose). Everything the policy sees (proprioception, images,
actions) is therefore in the base frame, and the base pose itself is never observed.

Geometry: with an aimed base pose (`shiftkit.envs.base_pose`) the task centre sits at the camera's
aim point, `AIM` = (0, 0.5, 0.125) in the base frame, where the Panda reaches comfortably with its
hand pointing down. The camera is 0.6 m up beside the arm, 0.83 m from the centre, looking down at
it (64x48, fovy 70 deg).
"""

from __future__ import annotations

from collections.abc import Callable

import mujoco
import numpy as np

from shiftkit.envs.base_pose import AIM, CAMERA_NAME, CAMERA_POS, SAMPLER, TABLE_Z, BasePose
from shiftkit.envs.cameras import look_at
from shiftkit.envs.controllers import FixedOrientationIK
from shiftkit.envs.geometry import quat_wxyz_to_xyzw, quat_xyzw, rotation_from_vector, rotation_z, yaw_quat_wxyz
from shiftkit.envs.panda_model import panda_spec
from shiftkit.envs.scene import SCENE_GROUP, add_box, add_light_and_ground

PHYSICS_DT = 0.002
TICK_SUBSTEPS = 25  # the Cartesian controller's 50 ms tick
CONTROL_HZ = 10
MAX_TCP_SPEED = 0.25  # m/s at |action| = 1: 2.5 cm per 10 Hz step
MAX_TCP_ROT_SPEED = 1.0  # rad/s at |action| = 1: 0.1 rad per step
FINGER_OPEN = 0.04
# TCP 1.5 cm above the fingertips along the flange z axis (fingers slide along the site's y axis)
TCP_OFFSET = 0.2475
# hand pointing down, fingers closing along base x
TCP_ROTATION = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# IK solution for the TCP at (0, 0.5, 0.22) in TCP_ROTATION (kitchen_franka joint conventions)
HOME_QPOS = np.array([1.5908, -0.0527, -0.0199, -2.3267, -0.001, 0.7041, 0.0013])

TABLE_HALF = 0.3
CAMERA_FOVY = 70.0
# TCP bounds in the base frame around the aim point (the base noise moves the centre by < 3 cm)
WORKSPACE_LOW = AIM + [-0.22, -0.2, 0.005]
WORKSPACE_HIGH = AIM + [0.22, 0.2, 0.3]


# geom groups: robot visual meshes 0, scene 1, robot collision 3 (the fast render mode shows 1 and 3)

BLOCK_HALF = 0.02
CYLINDER_RADIUS = 0.015
CYLINDER_HALF_LENGTH = 0.04
HOLE_CLEARANCE = 0.001  # per side: the thesis' "< 1 mm tolerance"
HOLE_DEPTH = 0.04
HOLE_XY = np.array([0.08, 0.0])  # task frame, relative to the centre
DOOR_WIDTH = 0.2
DOOR_HEIGHT = 0.12
DOOR_HINGE_XY = np.array([0.1, 0.08])  # task frame: the door spans x in [-0.1, 0.1] at y = 0.08, closed
HANDLE_RADIUS = 0.01
HANDLE_OFFSET = np.array([-0.17, -0.035])  # handle post from the hinge, door frame (closed: along -x)
HANDLE_TOP = 0.06  # the post rises this far above the door's top edge

_OBJECTS = {
    "block": dict(kind="box", size=(BLOCK_HALF,) * 3, rgba=(0.9, 0.2, 0.2, 1.0), mass=0.1),
    "blue": dict(kind="box", size=(BLOCK_HALF,) * 3, rgba=(0.1, 0.2, 0.9, 1.0), mass=0.1),
    "green": dict(kind="box", size=(BLOCK_HALF,) * 3, rgba=(0.1, 0.8, 0.2, 1.0), mass=0.1),
    "cylinder": dict(
        kind="cylinder", size=(CYLINDER_RADIUS, CYLINDER_HALF_LENGTH, 0), rgba=(0.9, 0.6, 0.1, 1.0), mass=0.05
    ),
}


def _add_robot_and_camera(spec: mujoco.MjSpec) -> None:
    for body in spec.bodies:
        if body.name.startswith("panda0_"):
            body.gravcomp = 1.0
    for geom in spec.geoms:
        if geom.group == 3 and geom.parent.name not in ("panda0_link7", "panda0_leftfinger", "panda0_rightfinger"):
            geom.contype = geom.conaffinity = 0  # only hand + fingers reach the table
    for joint in spec.joints:
        if joint.name.startswith("robot:panda0_finger"):
            joint.armature = 0.05
            joint.damping = [10.0, 0.0, 0.0]
    for geom in spec.geoms:
        if geom.parent.name in ("panda0_leftfinger", "panda0_rightfinger") and geom.group == 3:
            geom.friction = [1.0, 0.005, 0.0001]
            geom.condim = 4
            geom.rgba = [0.5, 0.6, 0.7, 1.0]
    tcp = spec.body("panda0_link7").add_site()
    tcp.name = "tcp"
    tcp.pos = [0.0, 0.0, TCP_OFFSET]
    tcp.quat = [0.9238795, 0.0, 0.0, -0.3826834]
    tcp.size = [0.005] * 3
    tcp.group = 5
    world = spec.worldbody
    # the mobile base platform (visual only)
    add_box(world, "base_platform", (0.25, 0.3, 0.02), (0.1, -0.1, 0.02), (0.2, 0.2, 0.22, 1.0), collide=False)
    camera = world.add_camera()
    camera.name = CAMERA_NAME
    camera.pos = list(CAMERA_POS)
    camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    camera.alt.xyaxes = list(look_at(CAMERA_POS, AIM))
    camera.fovy = CAMERA_FOVY


def _add_task_frame(spec: mujoco.MjSpec, task: str) -> None:
    """The world part that moves with the base pose: table (+ hole fixture or door)."""
    frame = spec.worldbody.add_body()
    frame.name = "task_frame"
    # table: top at TABLE_Z, with a pattern so the view change shows in the images
    add_box(frame, "table", (TABLE_HALF, TABLE_HALF, TABLE_Z / 2), (0, 0, TABLE_Z / 2), (0.55, 0.45, 0.35, 1.0))
    for i, (x, y) in enumerate(((-0.2, 0.2), (0.2, 0.2), (-0.2, -0.2), (0.2, -0.2))):
        add_box(
            frame, f"table_mark{i}", (0.03, 0.03, 0.0005), (x, y, TABLE_Z + 0.0006), (0.1, 0.1, 0.1, 1.0), collide=False
        )
    if task == "pick-insert":
        inner = CYLINDER_RADIUS + HOLE_CLEARANCE
        wall = 0.03
        z = TABLE_Z + HOLE_DEPTH / 2
        grey = (0.4, 0.4, 0.45, 1.0)
        hx, hy = HOLE_XY
        for name, half, off in (
            ("n", (inner + wall, wall / 2, HOLE_DEPTH / 2), (0, inner + wall / 2)),
            ("s", (inner + wall, wall / 2, HOLE_DEPTH / 2), (0, -inner - wall / 2)),
            ("e", (wall / 2, inner, HOLE_DEPTH / 2), (inner + wall / 2, 0)),
            ("w", (wall / 2, inner, HOLE_DEPTH / 2), (-inner - wall / 2, 0)),
        ):
            add_box(frame, f"hole_{name}", half, (hx + off[0], hy + off[1], z), grey)
    if task == "door":
        # a frame post at the hinge, and a door panel on a damped, sprung vertical hinge
        post_h = DOOR_HEIGHT + 0.04
        hx, hy = DOOR_HINGE_XY
        add_box(
            frame, "door_post", (0.01, 0.03, post_h / 2), (hx + 0.025, hy, TABLE_Z + post_h / 2), (0.3, 0.3, 0.3, 1)
        )
        door = frame.add_body()
        door.name = "door"
        door.pos = [hx, hy, TABLE_Z + 0.002]
        hinge = door.add_joint()
        hinge.name = "door_hinge"
        hinge.type = mujoco.mjtJoint.mjJNT_HINGE
        hinge.axis = [0, 0, 1]
        hinge.range = [0.0, 2.2]
        hinge.limited = mujoco.mjtLimited.mjLIMITED_TRUE
        hinge.damping = [0.5, 0, 0]
        hinge.stiffness = [0.1, 0, 0]  # a weak spring closing the door
        hinge.frictionloss = 0.02
        panel = add_box(
            door,
            "door_panel",
            (DOOR_WIDTH / 2, 0.008, DOOR_HEIGHT / 2),
            (-DOOR_WIDTH / 2, 0, DOOR_HEIGHT / 2),
            (0.7, 0.55, 0.3, 1.0),
        )
        panel.mass = 0.5
        handle = door.add_geom()
        handle.name = "door_handle"
        handle.type = mujoco.mjtGeom.mjGEOM_CYLINDER
        top = DOOR_HEIGHT + HANDLE_TOP
        handle.size = [HANDLE_RADIUS, top / 2 - 0.02, 0]
        handle.pos = [*HANDLE_OFFSET, top / 2 + 0.02]
        handle.rgba = [0.8, 0.8, 0.85, 1.0]
        handle.group = SCENE_GROUP
        handle.condim = 3  # the post may turn inside a closed grasp as the door swings
        handle.mass = 0.05
        # arm from the panel to the post
        add_box(
            door,
            "door_handle_arm",
            (0.01, abs(HANDLE_OFFSET[1]) / 2, 0.01),
            (HANDLE_OFFSET[0], HANDLE_OFFSET[1] / 2, DOOR_HEIGHT - 0.02),
            (0.8, 0.8, 0.85, 1.0),
        )


def _add_objects(spec: mujoco.MjSpec, names: tuple[str, ...]) -> None:
    for name in names:
        o = _OBJECTS[name]
        body = spec.worldbody.add_body()
        body.name = name
        body.pos = [0.0, 0.5, 0.6]
        joint = body.add_freejoint()
        joint.name = f"{name}_free"
        g = body.add_geom()
        g.name = f"{name}_geom"
        g.type = mujoco.mjtGeom.mjGEOM_BOX if o["kind"] == "box" else mujoco.mjtGeom.mjGEOM_CYLINDER
        g.size = list(o["size"])
        g.rgba = list(o["rgba"])
        g.mass = o["mass"]
        # torsional friction keeps a grasped object from pivoting about the finger axis
        g.friction = [1.0, 0.02, 0.0001]
        g.condim = 4
        g.group = SCENE_GROUP


def build_spec(model_id: str, task: str, objects: tuple[str, ...]) -> mujoco.MjSpec:
    """The scene's MjSpec: the Panda with its camera, the task frame and `objects`."""
    spec = panda_spec(model_id, timestep=PHYSICS_DT, impratio=10.0)
    spec.visual.quality.numslices = 10
    spec.visual.quality.numstacks = 4
    add_light_and_ground(spec.worldbody, [0.0, 0.4, 1.5], [0.0, 0.0, -1.0], ground_half=3.0)
    _add_robot_and_camera(spec)
    _add_task_frame(spec, task)
    _add_objects(spec, objects)
    return spec


class MultiviewPhysics:
    """MuJoCo model/data of one multiview task scene, its base pose and Cartesian 6-DOF controller."""

    def __init__(self, model_id: str, task: str, objects: tuple[str, ...]) -> None:
        self.model = build_spec(model_id, task, objects).compile()
        self.data = mujoco.MjData(self.model)
        self._ik_data = mujoco.MjData(self.model)
        m = self.model
        self.n_substeps = int(round(1.0 / (CONTROL_HZ * PHYSICS_DT)))
        self.n_ticks = self.n_substeps // TICK_SUBSTEPS
        self.tcp_site = m.site("tcp").id
        arm = [m.joint(f"robot:panda0_joint{i}") for i in range(1, 8)]
        self.arm_qpos = slice(arm[0].qposadr[0], arm[0].qposadr[0] + 7)
        self.arm_dofs = slice(arm[0].dofadr[0], arm[0].dofadr[0] + 7)
        self.arm_low, self.arm_high = np.array([j.range for j in arm]).T.copy()
        finger = m.joint("robot:panda0_finger_joint1").qposadr[0]
        self.finger_qpos = slice(finger, finger + 2)
        self.objects = objects
        self.object_body = {n: m.body(n).id for n in objects}
        self.object_qpos = {n: m.joint(f"{n}_free").qposadr[0] for n in objects}
        self.object_dof = {n: m.joint(f"{n}_free").dofadr[0] for n in objects}
        self.object_geom = {n: m.geom(f"{n}_geom").id for n in objects}
        self.finger_geoms = {
            side: {g for g in range(m.ngeom) if m.geom_bodyid[g] == m.body(f"panda0_{side}finger").id}
            for side in ("left", "right")
        }
        self.frame_body = m.body("task_frame").id
        self.door_qpos = m.joint("door_hinge").qposadr[0] if task == "door" else None
        self.camera = m.camera(CAMERA_NAME).id
        self.base_pose = SAMPLER.centre_pose()
        self.desired_tcp = np.zeros(3)
        self.desired_rot = TCP_ROTATION.copy()
        self.q_target = HOME_QPOS.copy()
        self.gripper_closed = False
        self.finger_history = np.ones((3, 2))  # rows t-2, t-1, t
        self._ik = self._make_ik(TCP_ROTATION)

    # ----------------------------------------------------------------- base pose
    def set_base_pose(self, pose: BasePose) -> None:
        """Place the world (table and fixtures) so that the base stands at `pose` (kinematics
        updated; free objects keep their base-frame qpos)."""
        self.base_pose = pose
        inverse_rot = -pose.yaw
        origin = -(rotation_z(inverse_rot) @ [pose.x, pose.y, 0.0])
        self.model.body_pos[self.frame_body] = origin
        self.model.body_quat[self.frame_body] = yaw_quat_wxyz(inverse_rot)
        mujoco.mj_forward(self.model, self.data)

    def world_to_base(self, points: np.ndarray) -> np.ndarray:
        """World-frame points (..., 3) in the base frame."""
        return self.base_pose.to_base(points)

    # ----------------------------------------------------------------- state access
    def tcp_pos(self) -> np.ndarray:
        """TCP position (3,), base frame (m)."""
        return self.data.site_xpos[self.tcp_site].copy()

    def tcp_rot(self) -> np.ndarray:
        """TCP rotation (3, 3), base frame."""
        return self.data.site_xmat[self.tcp_site].reshape(3, 3).copy()

    def object_pos(self, name: str) -> np.ndarray:
        """Position (3,) of object `name`, base frame (m)."""
        return self.data.xpos[self.object_body[name]].copy()

    def object_rot(self, name: str) -> np.ndarray:
        """Rotation (3, 3) of object `name`, base frame."""
        return self.data.xmat[self.object_body[name]].reshape(3, 3).copy()

    def door_angle(self) -> float:
        """Door hinge angle (rad)."""
        return float(self.data.qpos[self.door_qpos])

    def handle_pos(self) -> np.ndarray:
        """Door handle position (3,), base frame (m)."""
        return self.data.geom_xpos[self.model.geom("door_handle").id].copy()

    def hinge_pos(self) -> np.ndarray:
        """Door body origin (on its hinge) (3,), base frame (m)."""
        return self.data.xpos[self.model.body("door").id].copy()

    def fingers(self) -> np.ndarray:
        """Finger joint positions as a fraction of fully open (1: open)."""
        return self.data.qpos[self.finger_qpos] / FINGER_OPEN

    def touching(self, geom: int, side: str) -> bool:
        """Whether `geom` touches the finger on `side` ("left" or "right")."""
        d = self.data
        fingers = self.finger_geoms[side]
        for c in d.contact[: d.ncon] if d.ncon else ():
            if (c.geom1 == geom and c.geom2 in fingers) or (c.geom2 == geom and c.geom1 in fingers):
                return True
        return False

    def holding(self, geom: int) -> bool:
        """Whether the closed gripper holds `geom` between both fingers."""
        return self.gripper_closed and self.touching(geom, "left") and self.touching(geom, "right")

    def in_contact(self, geom_a: int, geom_b: int) -> bool:
        """Whether geoms `geom_a` and `geom_b` are in contact."""
        d = self.data
        for i in range(d.ncon):
            pair = (d.contact.geom1[i], d.contact.geom2[i])
            if pair in ((geom_a, geom_b), (geom_b, geom_a)):
                return True
        return False

    # ----------------------------------------------------------------- reset
    def place_object(self, name: str, world_xy: np.ndarray, z: float, yaw: float) -> None:
        """Put a free object at a task-frame (world) position with a yaw, in the base-frame qpos."""
        pose = self.base_pose
        pos = pose.to_base(np.array([*world_xy, z]))
        a = self.object_qpos[name]
        self.data.qpos[a : a + 3] = pos
        self.data.qpos[a + 3 : a + 7] = yaw_quat_wxyz(yaw - pose.yaw)

    def reset(self, pose: BasePose, place: Callable[[MultiviewPhysics], np.ndarray]) -> None:
        """Reset at base pose `pose`: `place(self)` puts the objects and returns the base-frame TCP
        start, where the hand goes pointing down, gripper open; contacts settle."""
        d = self.data
        mujoco.mj_resetData(self.model, d)
        self.set_base_pose(pose)
        tcp = place(self)
        d.qpos[self.finger_qpos] = FINGER_OPEN
        self.desired_rot = TCP_ROTATION.copy()
        self._ik = self._make_ik(TCP_ROTATION)
        d.qpos[self.arm_qpos] = self.solve_arm(tcp, TCP_ROTATION, HOME_QPOS, iterations=40)
        self.q_target = d.qpos[self.arm_qpos].copy()
        self.desired_tcp = np.asarray(tcp, dtype=np.float64).copy()
        self.gripper_closed = False
        self._write_controls()
        mujoco.mj_forward(self.model, d)
        mujoco.mj_step(self.model, d, nstep=25)
        d.qvel[:] = 0.0
        mujoco.mj_forward(self.model, d)
        self.finger_history[:] = self.fingers()

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Restore a simulator state recorded at the current base pose."""
        self.data.qpos[:] = qpos
        self.data.qvel[:] = qvel
        self.q_target = self.data.qpos[self.arm_qpos].copy()
        mujoco.mj_forward(self.model, self.data)
        self.desired_tcp = self.tcp_pos()
        self.desired_rot = self.tcp_rot()
        self._ik = self._make_ik(self.desired_rot)
        self.gripper_closed = bool(self.fingers().mean() < 0.9)
        self._write_controls()
        self.finger_history[:] = self.fingers()

    # ----------------------------------------------------------------- IK and control
    def _make_ik(self, rotation: np.ndarray) -> FixedOrientationIK:
        return FixedOrientationIK(
            self.model,
            self.tcp_site,
            self.arm_qpos,
            self.arm_dofs,
            rotation,
            HOME_QPOS,
            self.arm_low,
            self.arm_high,
        )

    def solve_arm(self, tcp: np.ndarray, rotation: np.ndarray, q0: np.ndarray, iterations: int = 30) -> np.ndarray:
        """Arm joint positions placing the TCP at `tcp` with hand rotation `rotation` (base frame),
        by damped least-squares iterations from `q0` on a scratch `MjData`."""
        ik = self._make_ik(rotation)
        self._ik_data.qpos[:] = self.data.qpos
        q = np.asarray(q0, dtype=np.float64).copy()
        for _ in range(iterations):
            q = ik.step(self._ik_data, q, np.asarray(tcp, dtype=np.float64))
        return q

    def tcp_error(self, q: np.ndarray, tcp: np.ndarray, rotation: np.ndarray) -> tuple[float, float]:
        """Position (m) and rotation (rad) error of the TCP at joint positions `q`."""
        d = self._ik_data
        d.qpos[self.arm_qpos] = q
        mujoco.mj_kinematics(self.model, d)
        pos_err = float(np.linalg.norm(d.site_xpos[self.tcp_site] - tcp))
        rot = d.site_xmat[self.tcp_site].reshape(3, 3)
        cos = (np.trace(rot.T @ rotation) - 1.0) / 2.0
        return pos_err, float(np.arccos(np.clip(cos, -1.0, 1.0)))

    def _write_controls(self) -> None:
        self.data.ctrl[:7] = self.q_target
        self.data.ctrl[7:9] = 0.0 if self.gripper_closed else FINGER_OPEN

    def step(self, move: np.ndarray, rotate: np.ndarray, gripper: float) -> None:
        """One 10 Hz control step: TCP velocity `move` and angular velocity `rotate` (base frame,
        each in [-1, 1] of the maximum), gripper > 0 opens, < 0 closes, 0 keeps."""
        if gripper != 0.0:
            self.gripper_closed = gripper < 0.0
        tick_dt = TICK_SUBSTEPS * PHYSICS_DT
        if np.any(rotate):
            turn = rotation_from_vector(np.asarray(rotate, np.float64) * MAX_TCP_ROT_SPEED * tick_dt * self.n_ticks)
            self.desired_rot = turn @ self.desired_rot
            self._ik = self._make_ik(self.desired_rot)
        for _ in range(self.n_ticks):
            self.desired_tcp = (self.desired_tcp + move * MAX_TCP_SPEED * tick_dt).clip(WORKSPACE_LOW, WORKSPACE_HIGH)
            self.q_target = self._ik.step(self._ik_data, self.q_target, self.desired_tcp)
            self._write_controls()
            mujoco.mj_step(self.model, self.data, nstep=TICK_SUBSTEPS)
        mujoco.mj_forward(self.model, self.data)
        self.finger_history[:2] = self.finger_history[1:]
        self.finger_history[2] = self.fingers()

    # ----------------------------------------------------------------- observation
    def proprioception(self) -> np.ndarray:
        """TCP position, orientation (xyzw) and fingers now, t-1, t-2: 13 numbers, base frame."""
        h = self.finger_history
        return np.concatenate([self.tcp_pos(), quat_xyzw(self.tcp_rot()), h[2], h[1], h[0]])

    def object_state(self) -> np.ndarray:
        """Pose of each free object (position + xyzw quaternion), then the door's handle position
        and hinge angle when there is a door: base frame."""
        parts = []
        for name in self.objects:
            parts += [self.object_pos(name), quat_wxyz_to_xyzw(self.data.xquat[self.object_body[name]])]
        if self.door_qpos is not None:
            parts += [self.handle_pos(), [self.door_angle()]]
        return np.concatenate(parts) if parts else np.zeros(0)


def rebase_state(
    physics: MultiviewPhysics, qpos: np.ndarray, qvel: np.ndarray, old: BasePose, new: BasePose
) -> tuple[np.ndarray, np.ndarray]:
    """A recorded state with its free objects moved from base pose `old` to base pose `new` (they
    keep their world poses and velocities); arm, fingers and hinge are copied unchanged."""
    out_q, out_v = np.array(qpos, dtype=np.float64), np.array(qvel, dtype=np.float64)
    rel = rotation_z(old.yaw - new.yaw)  # old base axes in the new base frame
    quat = np.zeros(4)
    for name in physics.objects:
        a, v = physics.object_qpos[name], physics.object_dof[name]
        out_q[a : a + 3] = new.to_base(old.to_world(qpos[a : a + 3]))
        mujoco.mju_mulQuat(quat, yaw_quat_wxyz(old.yaw - new.yaw), qpos[a + 3 : a + 7])
        out_q[a + 3 : a + 7] = quat
        out_v[v : v + 3] = rel @ qvel[v : v + 3]  # linear velocity in the frame; angular is body-local
    return out_q, out_v
