"""Panda play scene: composition with `mujoco.MjSpec`, Cartesian control and the 59-dim observation.

Physics only, no task logic (tasks live in `tasks`). Numbers follow the reference
environment (utiasSTARS/manipulator-learning, `PandaPlayInsertTrayXYZState`) and the LfGP thesis,
appendix A.1. Everything is expressed in the robot base frame, which here *is* the MuJoCo world
frame (robot base at the origin, identity orientation), the frame the published VPACE data use:

* tray floor top at z = 0.125 m, centred at (0, 0.5); 30x30 cm floor with 45-degree sloped edges;
* a resting 4 cm block has its centre at z = 0.145 (the reference's "table height");
* bring targets (the reference's coaster origins) at (+-0.075, 0.5, 0.125), blue at +x;
* insertion slots 4.1x4.1x1 cm centred under the bring targets; an inserted block's centre is at
  (+-0.075, 0.5, 0.135);
* tool centre point (TCP) bounds x in [-0.15, 0.15], y in [0.35, 0.65], z in [0.145, 0.28].

The robot is the gymnasium-robotics Franka Panda (`shiftkit.envs.panda_model`); the controller is
the shared fixed-orientation differential IK (`shiftkit.envs.controllers`) feeding position servos.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from shiftkit.envs.cameras import look_at
from shiftkit.envs.controllers import FixedOrientationIK
from shiftkit.envs.panda_model import panda_spec
from shiftkit.envs.scene import add_box, add_light_and_ground

SIM_MODEL_ID = "panda-play-v1"

TRAY_CENTER = np.array([0.0, 0.5])
TRAY_HALF = 0.15
TRAY_FLOOR_Z = 0.125
SLOPE_WIDTH = 0.09
BLOCK_HALF = 0.02
BLOCK_MASS = 0.1
BLOCK_REST_Z = TRAY_FLOOR_Z + BLOCK_HALF
SLOT_HALF = 0.0205
SLOT_DEPTH = 0.01
ZONE_HALF = 0.04
# index 0 = blue, 1 = green (the reference's object order)
ZONE_XY = np.array([[0.075, 0.5], [-0.075, 0.5]])
BRING_TARGETS = np.column_stack([ZONE_XY, np.full(2, TRAY_FLOOR_Z)])
INSERT_TARGETS = np.column_stack([ZONE_XY, np.full(2, BLOCK_REST_Z - SLOT_DEPTH)])
WORKSPACE_LOW = np.array([-0.15, 0.35, BLOCK_REST_Z])
WORKSPACE_HIGH = np.array([0.15, 0.65, 0.28])
# reset distributions (reference: 15x15 cm squares at the tray centre; EE 5-14.5 cm above the floor)
BLOCK_SPAWN_HALF = 0.075
BLOCK_MIN_SEPARATION = 0.065
EE_SPAWN_HALF = 0.075
EE_SPAWN_Z = (TRAY_FLOOR_Z + 0.05, min(TRAY_FLOOR_Z + 0.145, WORKSPACE_HIGH[2]))

PHYSICS_DT = 0.002
# |action| = 1 moves the desired TCP by 2 mm per 10 ms (reference: 0.002 m per 0.01 s substep),
# i.e. 1 cm per step at 20 Hz and 4 cm per step at 5 Hz
MAX_TCP_SPEED = 0.2
# The Cartesian controller runs at 20 Hz (50 ms ticks of 25 physics steps): an action is held
# for the whole control period, the desired TCP advancing every tick, as the reference advances
# it every 10 ms substep (a 5 Hz action moves the arm steadily, not in one 4 cm jump).
TICK_SUBSTEPS = 25
FINGER_OPEN = 0.04
# TCP distance from the link7 flange along its z axis: 1.5 cm above the (1.75x long) fingertips,
# so a block grasped at its centre sits fully between the pads and the tips clear the floor
TCP_OFFSET = 0.2475
# hand orientation held fixed: fingers open along base x, gripper pointing down
TCP_ROTATION = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# IK solution for the TCP at (0, 0.5, 0.22) in TCP_ROTATION (kitchen_franka joint conventions)
HOME_QPOS = np.array([1.5908, -0.0527, -0.0199, -2.3267, -0.001, 0.7041, 0.0013])

OBSERVATION_NAMES: tuple[str, ...] = (
    "ee_pos_x",
    "ee_pos_y",
    "ee_pos_z",
    "ee_vel_x",
    "ee_vel_y",
    "ee_vel_z",
    "finger_left",
    "finger_right",
    "finger_left_t-2",
    "finger_right_t-2",
    "finger_left_t-1",
    "finger_right_t-1",
    "blue_pos_x",
    "blue_pos_y",
    "blue_pos_z",
    "blue_quat_x",
    "blue_quat_y",
    "blue_quat_z",
    "blue_quat_w",
    "green_pos_x",
    "green_pos_y",
    "green_pos_z",
    "green_quat_x",
    "green_quat_y",
    "green_quat_z",
    "green_quat_w",
    "blue_linvel_x",
    "blue_linvel_y",
    "blue_linvel_z",
    "blue_angvel_x",
    "blue_angvel_y",
    "blue_angvel_z",
    "green_linvel_x",
    "green_linvel_y",
    "green_linvel_z",
    "green_angvel_x",
    "green_angvel_y",
    "green_angvel_z",
    "blue_minus_ee_x",
    "blue_minus_ee_y",
    "blue_minus_ee_z",
    "green_minus_ee_x",
    "green_minus_ee_y",
    "green_minus_ee_z",
    "green_minus_blue_x",
    "green_minus_blue_y",
    "green_minus_blue_z",
    "blue_target_minus_blue_x",
    "blue_target_minus_blue_y",
    "blue_target_minus_blue_z",
    "green_target_minus_green_x",
    "green_target_minus_green_y",
    "green_target_minus_green_z",
    "wrist_force_x",
    "wrist_force_y",
    "wrist_force_z",
    "wrist_torque_x",
    "wrist_torque_y",
    "wrist_torque_z",
)
OBS_DIM = len(OBSERVATION_NAMES)
# dataset split: robot proprioception vs privileged object state (full = state[:12] + env + state[12:])
STATE_INDICES = np.r_[0:12, 53:59]
ENVIRONMENT_STATE_INDICES = np.r_[12:53]
# gripper: > 0 opens, < 0 closes (thesis appendix A.1, docs/panda_play.md; the published VPACE data use the opposite sign, see
# `vpace_compat`)
ACTION_NAMES = ("delta_x", "delta_y", "delta_z", "gripper_open")

FINGER_FRICTION = 0.3
BLOCK_FRICTION = 0.5


CAMERAS = {
    # across the tray, looking back at the robot (the reference's workspace camera view)
    "front": dict(pos=(0.0, 1.05, 0.5), target=(0.0, 0.48, 0.13), fovy=55.0),
    "overhead": dict(pos=(0.0, 0.62, 0.75), target=(0.0, 0.5, 0.125), fovy=45.0),
}


def build_spec() -> mujoco.MjSpec:
    """Compose the scene: gymnasium-robotics Panda + tray with slots + two blocks + cameras."""
    # stiffer friction: grasped blocks do not creep out of the fingers
    spec = panda_spec(SIM_MODEL_ID, timestep=PHYSICS_DT, impratio=10.0)
    # the finger collision shapes are 24 capsules: coarse tessellation keeps 64x48 renders cheap
    spec.visual.quality.numslices = 10
    spec.visual.quality.numstacks = 4

    for body in spec.bodies:
        if body.name.startswith("panda0_"):
            body.gravcomp = 1.0  # position servos then track without gravity sag
    for geom in spec.geoms:
        # the upper arm never reaches the tray inside the TCP bounds: only hand + fingers collide
        body = geom.parent.name
        if geom.group == 3 and body not in ("panda0_link7", "panda0_leftfinger", "panda0_rightfinger"):
            geom.contype = geom.conaffinity = 0
    for joint in spec.joints:
        if joint.name.startswith("robot:panda0_finger"):
            joint.armature = 0.05  # the kitchen model's 5 kg-equivalent fingers need ~1 s to close
            joint.damping = [10.0, 0.0, 0.0]
    for geom in spec.geoms:
        if geom.parent.name in ("panda0_leftfinger", "panda0_rightfinger") and geom.group == 3:
            # the kitchen model's torsional friction (0.5 m) pins grasped blocks; with these
            # values closing fingers square a rotated block up against the pads
            geom.friction = [FINGER_FRICTION, 0.005, 0.0001]
            geom.condim = 4
            geom.rgba = [0.5, 0.6, 0.7, 1.0]  # opaque: transparent geoms cost a sorted extra pass
    link7 = spec.body("panda0_link7")
    tcp = link7.add_site()
    tcp.name = "tcp"
    tcp.pos = [0.0, 0.0, TCP_OFFSET]
    tcp.quat = [0.9238795, 0.0, 0.0, -0.3826834]  # hand frame: fingers slide along site y
    tcp.size = [0.005, 0.005, 0.005]
    tcp.group = 5

    world = spec.worldbody
    add_light_and_ground(world, [0.0, 0.6, 1.5], [0.0, -0.2, -1.0])

    tray = world.add_body()
    tray.name = "tray"
    tray.pos = [TRAY_CENTER[0], TRAY_CENTER[1], 0.0]
    grey = (0.55, 0.55, 0.58, 1.0)
    base_top = TRAY_FLOOR_Z - SLOT_DEPTH
    add_box(
        tray,
        "tray_pedestal",
        (TRAY_HALF + SLOPE_WIDTH, TRAY_HALF + SLOPE_WIDTH, base_top / 2),
        (0, 0, base_top / 2),
        (0.4, 0.3, 0.25, 1.0),
    )
    # the top 1 cm layer of the floor, cut around the two slots
    h = SLOT_DEPTH / 2
    z = base_top + h
    band = (TRAY_HALF - SLOT_HALF) / 2
    add_box(tray, "tray_floor_near", (TRAY_HALF, band, h), (0, -SLOT_HALF - band, z), grey)
    add_box(tray, "tray_floor_far", (TRAY_HALF, band, h), (0, SLOT_HALF + band, z), grey)
    zx = ZONE_XY[0, 0]
    outer = (TRAY_HALF - zx - SLOT_HALF) / 2
    inner = zx - SLOT_HALF
    add_box(tray, "tray_floor_mid", (inner, SLOT_HALF, h), (0, 0, z), grey)
    add_box(tray, "tray_floor_pos", (outer, SLOT_HALF, h), (zx + SLOT_HALF + outer, 0, z), grey)
    add_box(tray, "tray_floor_neg", (outer, SLOT_HALF, h), (-zx - SLOT_HALF - outer, 0, z), grey)
    # 45-degree slopes rising from the floor edges
    t = 0.005
    length = SLOPE_WIDTH * np.sqrt(2.0)
    c = TRAY_HALF + SLOPE_WIDTH / 2 + t / np.sqrt(2.0)
    zc = TRAY_FLOOR_Z + SLOPE_WIDTH / 2 - t / np.sqrt(2.0)
    s = np.sin(np.pi / 8)
    k = np.cos(np.pi / 8)
    long_half = TRAY_HALF + SLOPE_WIDTH
    for name, pos, quat, half in (
        ("tray_slope_far", (0, c, zc), (k, s, 0, 0), (long_half, length / 2, t)),
        ("tray_slope_near", (0, -c, zc), (k, -s, 0, 0), (long_half, length / 2, t)),
        ("tray_slope_right", (c, 0, zc), (k, 0, -s, 0), (length / 2, long_half, t)),
        ("tray_slope_left", (-c, 0, zc), (k, 0, s, 0), (length / 2, long_half, t)),
    ):
        add_box(tray, name, half, pos, (0.6, 0.6, 0.63, 1.0), quat=quat)
    # bring zones: thin visual squares on the floor (no collision)
    for i, rgba in enumerate(((0, 0, 1, 0.25), (0, 1, 0, 0.25))):
        dx = ZONE_XY[i, 0] - TRAY_CENTER[0]
        add_box(
            tray,
            f"zone_{'blue' if i == 0 else 'green'}",
            (ZONE_HALF, ZONE_HALF, 0.0005),
            (dx, 0, TRAY_FLOOR_Z + 0.0006),
            rgba,
            collide=False,
        )

    for name, rgba in (("blue", (0, 0, 1, 1)), ("green", (0, 1, 0, 1))):
        block = world.add_body()
        block.name = f"{name}_block"
        block.pos = [0.0, 0.5, 0.5]
        joint = block.add_freejoint()
        joint.name = f"{name}_free"
        g = add_box(block, f"{name}_geom", (BLOCK_HALF,) * 3, (0, 0, 0), rgba)
        g.mass = BLOCK_MASS
        g.friction = [BLOCK_FRICTION, 0.005, 0.0001]
        g.condim = 4

    for name, cam in CAMERAS.items():
        camera = world.add_camera()
        camera.name = name
        camera.pos = list(cam["pos"])
        camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
        camera.alt.xyaxes = list(look_at(cam["pos"], cam["target"]))
        camera.fovy = cam["fovy"]
    return spec


# tanh squashing of the wrist force (scale 100 N) and torque (10 Nm) in the observation
_INV_WRENCH_SCALE = 1.0 / np.array([100.0, 100.0, 100.0, 10.0, 10.0, 10.0])


def block_reset_quat(yaw: float) -> np.ndarray:
    """Reset orientation in MuJoCo wxyz: yaw about z after a half turn about x. The reference resets
    blocks as euler (pi, 0, yaw) (a cube looks the same either way); matching it keeps our reset
    quaternions, (cos(yaw/2), sin(yaw/2), 0, 0) in xyzw, on the published data's distribution."""
    return np.array([0.0, np.cos(yaw / 2), np.sin(yaw / 2), 0.0])


@dataclass
class ContactFlags:
    """Which pairs of scene parts touch (at the current MuJoCo state)."""

    blue_green: bool
    blue_tray: bool
    green_tray: bool
    blue_gripper: bool
    green_gripper: bool
    blue_left_finger: bool
    blue_right_finger: bool
    green_left_finger: bool
    green_right_finger: bool


# part codes for the contact table
_OTHER, _BLUE, _GREEN, _TRAY, _HAND, _LEFT, _RIGHT = range(7)
# one bit per ContactFlags field: the part pairs it looks at
_CONTACT_BITS = {
    "blue_green": ((_BLUE, _GREEN),),
    "blue_tray": ((_BLUE, _TRAY),),
    "green_tray": ((_GREEN, _TRAY),),
    "blue_gripper": ((_BLUE, _HAND), (_BLUE, _LEFT), (_BLUE, _RIGHT)),
    "green_gripper": ((_GREEN, _HAND), (_GREEN, _LEFT), (_GREEN, _RIGHT)),
    "blue_left_finger": ((_BLUE, _LEFT),),
    "blue_right_finger": ((_BLUE, _RIGHT),),
    "green_left_finger": ((_GREEN, _LEFT),),
    "green_right_finger": ((_GREEN, _RIGHT),),
}


class PandaPlayPhysics:
    """The MuJoCo model/data of the Panda play scene plus its Cartesian controller and observation."""

    def __init__(self, control_hz: int = 20) -> None:
        if control_hz not in (5, 20):
            raise ValueError(f"control_hz must be 5 or 20, got {control_hz}")
        self.control_hz = control_hz
        self.model = build_spec().compile()
        self.data = mujoco.MjData(self.model)
        self._ik = mujoco.MjData(self.model)
        self.n_substeps = int(round(1.0 / (control_hz * PHYSICS_DT)))
        self.n_ticks = self.n_substeps // TICK_SUBSTEPS
        self.control_dt = self.n_substeps * PHYSICS_DT
        self.max_step = MAX_TCP_SPEED * self.control_dt
        self._tick_step = MAX_TCP_SPEED * TICK_SUBSTEPS * PHYSICS_DT
        m = self.model
        self.tcp_site = m.site("tcp").id
        arm_joints = [m.joint(f"robot:panda0_joint{i}") for i in range(1, 8)]
        # the kitchen model lists the arm joints first: slices index faster than index arrays
        qadr, vadr = arm_joints[0].qposadr[0], arm_joints[0].dofadr[0]
        assert [j.qposadr[0] for j in arm_joints] == list(range(qadr, qadr + 7))
        assert [j.dofadr[0] for j in arm_joints] == list(range(vadr, vadr + 7))
        self.arm_qpos = slice(qadr, qadr + 7)
        self.arm_dofs = slice(vadr, vadr + 7)
        self.arm_low, self.arm_high = np.array([j.range for j in arm_joints]).T.copy()
        finger = m.joint("robot:panda0_finger_joint1").qposadr[0]
        assert m.joint("robot:panda0_finger_joint2").qposadr[0] == finger + 1
        self.finger_qpos = slice(finger, finger + 2)
        self.block_qpos = np.array([m.joint(f"{c}_free").qposadr[0] for c in ("blue", "green")])
        self.block_dof = np.array([m.joint(f"{c}_free").dofadr[0] for c in ("blue", "green")])
        self.block_body = np.array([m.body(f"{c}_block").id for c in ("blue", "green")])
        self._block_linvel_idx = np.concatenate([np.arange(a, a + 3) for a in self.block_dof])
        self._block_angvel_idx = self._block_linvel_idx + 3
        # flat indices of the block quaternions in xquat, reordered MuJoCo wxyz -> reference xyzw
        self._block_xyzw_idx = (4 * self.block_body[:, None] + [1, 2, 3, 0]).ravel()
        parts = np.full(m.ngeom, _OTHER, dtype=np.int64)
        parts[m.geom("blue_geom").id] = _BLUE
        parts[m.geom("green_geom").id] = _GREEN
        tray_body = m.body("tray").id
        for g in range(m.ngeom):
            body = m.geom_bodyid[g]
            if body == tray_body and m.geom_contype[g]:
                parts[g] = _TRAY
            elif body == m.body("panda0_link7").id:
                parts[g] = _HAND
            elif body == m.body("panda0_leftfinger").id:
                parts[g] = _LEFT
            elif body == m.body("panda0_rightfinger").id:
                parts[g] = _RIGHT
        self._gripper_part = np.isin(parts, (_HAND, _LEFT, _RIGHT))
        # geom pair -> bit mask of the ContactFlags fields a contact between them sets
        pair_bits = np.zeros((7, 7), dtype=np.int64)
        for bit, pairs in enumerate(_CONTACT_BITS.values()):
            for a, b in pairs:
                pair_bits[a, b] |= 1 << bit
                pair_bits[b, a] |= 1 << bit
        self._contact_bits = pair_bits[parts[:, None], parts[None, :]]
        self._controller = FixedOrientationIK(
            m, self.tcp_site, self.arm_qpos, self.arm_dofs, TCP_ROTATION, HOME_QPOS, self.arm_low, self.arm_high
        )
        self._vel6 = np.zeros(6)
        self.desired_tcp = np.zeros(3)
        self.q_target = HOME_QPOS.copy()
        self.gripper_closed = False
        self.finger_history = np.ones((3, 2))  # rows: t-2, t-1, t
        self.prev_block_vel = np.zeros((2, 3))
        self.block_acc = np.zeros((2, 3))

    # ----------------------------------------------------------------- state access
    def tcp_pos(self) -> np.ndarray:
        """TCP position (3,), world frame (m)."""
        return self.data.site_xpos[self.tcp_site].copy()

    def block_pos(self, i: int) -> np.ndarray:
        """Position (3,) of block `i` (0: blue, 1: green), world frame (m)."""
        return self.data.xpos[self.block_body[i]].copy()

    def block_quat_wxyz(self, i: int) -> np.ndarray:
        """Orientation of block `i` as a (w, x, y, z) quaternion, world frame."""
        return self.data.xquat[self.block_body[i]].copy()

    def block_tilt(self, i: int) -> float:
        """Angle (rad) between block `i`'s most vertical axis and the world z axis."""
        rot = self.data.xmat[self.block_body[i]].reshape(3, 3)
        return float(np.arccos(min(1.0, np.max(np.abs(rot[2])))))

    def block_yaw_error(self, i: int) -> float:
        """Angle (rad, in [-pi/4, pi/4)) between block `i`'s faces and the finger closing axis."""
        rot = self.data.xmat[self.block_body[i]].reshape(3, 3)
        axis = rot[:, int(np.argmin(np.abs(rot[2])))]  # the most horizontal block axis
        yaw = np.arctan2(axis[1], axis[0])
        return float((yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4)

    def block_linvels(self) -> np.ndarray:
        """(2, 3) linear velocities of blue and green."""
        return self.data.qvel[self._block_linvel_idx].reshape(2, 3)

    def fingers(self) -> np.ndarray:
        """Finger positions scaled to [0, 1] (1 = fully open), as in the reference."""
        return self.data.qpos[self.finger_qpos] / FINGER_OPEN

    def tcp_velocity(self) -> np.ndarray:
        """TCP linear velocity (3,), world frame (m/s)."""
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_SITE, self.tcp_site, self._vel6, 0)
        return self._vel6[3:].copy()

    # ----------------------------------------------------------------- reset
    def reset(self, rng: np.random.Generator, green_on_blue: bool = False) -> None:
        """Sample a reset state (blocks in the tray with random yaw, TCP 5-14.5 cm above the floor,
        gripper open) and settle it; every random number comes from `rng`."""
        d = self.data
        mujoco.mj_resetData(self.model, d)
        blue_xy = TRAY_CENTER + rng.uniform(-BLOCK_SPAWN_HALF, BLOCK_SPAWN_HALF, 2)
        while True:
            green_xy = TRAY_CENTER + rng.uniform(-BLOCK_SPAWN_HALF, BLOCK_SPAWN_HALF, 2)
            if green_on_blue or np.linalg.norm(green_xy - blue_xy) >= BLOCK_MIN_SEPARATION:
                break
        yaws = rng.uniform(0.0, 2 * np.pi, 2)
        tcp = np.array([*(TRAY_CENTER + rng.uniform(-EE_SPAWN_HALF, EE_SPAWN_HALF, 2)), rng.uniform(*EE_SPAWN_Z)])
        if green_on_blue:
            green_xy = blue_xy
            yaws[1] = yaws[0]
            green_z = BLOCK_REST_Z + 2 * BLOCK_HALF
            # keep the fingers clear of the tower
            tcp[2] = max(tcp[2], green_z + 0.06)
        else:
            green_z = BLOCK_REST_Z
        for i, (xy, z) in enumerate(((blue_xy, BLOCK_REST_Z), (green_xy, green_z))):
            a = self.block_qpos[i]
            d.qpos[a : a + 3] = (*xy, z + 1e-4)
            d.qpos[a + 3 : a + 7] = block_reset_quat(yaws[i])
        d.qpos[self.arm_qpos] = HOME_QPOS
        d.qpos[self.finger_qpos] = FINGER_OPEN
        self.q_target = HOME_QPOS.copy()
        for _ in range(30):
            self._ik_step(tcp, self.data)
            d.qpos[self.arm_qpos] = self.q_target
        self.desired_tcp = tcp.copy()
        self.gripper_closed = False
        self._write_controls()
        mujoco.mj_forward(self.model, d)
        # let contacts settle under the holding controller (blocks placed 0.1 mm above the floor)
        mujoco.mj_step(self.model, d, nstep=25)
        d.qvel[:] = 0.0
        mujoco.mj_forward(self.model, d)
        self.finger_history[:] = self.fingers()
        self.prev_block_vel[:] = self.block_linvels()
        self.block_acc[:] = 0.0

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Restore a simulator state (e.g. from a recorded `sim_qpos`/`sim_qvel`)."""
        self.data.qpos[:] = qpos
        self.data.qvel[:] = qvel
        self.q_target = self.data.qpos[self.arm_qpos].copy()
        mujoco.mj_forward(self.model, self.data)
        self.desired_tcp = self.tcp_pos()
        self.finger_history[:] = self.fingers()
        self.prev_block_vel[:] = self.block_linvels()

    def set_from_observation(self, obs: np.ndarray) -> None:
        """Place the scene at the first 12:26 + 0:12 dims of a reference observation: block poses
        as given (xyzw quaternions), the TCP at obs[0:3] by IK, fingers at obs[6:8]; velocities
        zero. Used to check published states against this scene's predicates."""
        d = self.data
        mujoco.mj_resetData(self.model, d)
        for i in range(2):
            a = self.block_qpos[i]
            o = 12 + 7 * i
            d.qpos[a : a + 3] = obs[o : o + 3]
            x, y, z, w = obs[o + 3 : o + 7]
            d.qpos[a + 3 : a + 7] = np.array([w, x, y, z]) / np.linalg.norm([w, x, y, z])
        d.qpos[self.finger_qpos] = np.asarray(obs[6:8]) * FINGER_OPEN
        self.q_target = HOME_QPOS.copy()
        for _ in range(40):
            self._ik_step(np.asarray(obs[0:3], dtype=np.float64), d)
        d.qpos[self.arm_qpos] = self.q_target
        self.desired_tcp = np.asarray(obs[0:3], dtype=np.float64).copy()
        self.gripper_closed = bool(obs[6] < 0.9)
        self._write_controls()
        mujoco.mj_forward(self.model, d)
        self.finger_history[:] = [obs[8:10], obs[10:12], obs[6:8]]
        self.prev_block_vel[:] = 0.0
        self.block_acc[:] = 0.0

    # ----------------------------------------------------------------- control
    def _ik_step(self, target: np.ndarray, data: mujoco.MjData) -> None:
        """One IK update of `q_target` towards the TCP `target` (fixed hand orientation), evaluated
        at `q_target` on `data` (kinematics only)."""
        self.q_target = self._controller.step(data, self.q_target, target)

    def _write_controls(self) -> None:
        self.data.ctrl[:7] = self.q_target
        self.data.ctrl[7:9] = 0.0 if self.gripper_closed else FINGER_OPEN

    def step(self, action: np.ndarray) -> None:
        """Apply one control step: delta TCP position (clipped to [-1, 1]; each 50 ms tick moves the
        desired position by up to 1 cm, kept inside the workspace bounds) and the gripper (> 0 opens,
        < 0 closes, 0 keeps)."""
        a = np.asarray(action, dtype=np.float64).clip(-1.0, 1.0)
        if a[3] != 0.0:
            self.gripper_closed = bool(a[3] < 0.0)
        move = a[:3] * self._tick_step
        m, d = self.model, self.data
        for tick in range(self.n_ticks):
            self.desired_tcp = (self.desired_tcp + move).clip(WORKSPACE_LOW, WORKSPACE_HIGH)
            self._ik_step(self.desired_tcp, self._ik)
            self._write_controls()
            if tick == 0:
                # Every method that changes the state ends with mj_forward, so the position and
                # velocity stages of the current state are up to date: the first substep recomputes
                # only what the new controls change (bitwise the same as mj_step), which pays for
                # the final forward below.
                mujoco.mj_forwardSkip(m, d, mujoco.mjtStage.mjSTAGE_VEL, 1)
                mujoco.mj_implicit(m, d)
                mujoco.mj_step(m, d, nstep=TICK_SUBSTEPS - 1)
            else:
                mujoco.mj_step(m, d, nstep=TICK_SUBSTEPS)
        # observation, contacts and predicates must describe the state that is returned
        mujoco.mj_forward(m, d)
        self.finger_history[:2] = self.finger_history[1:]
        self.finger_history[2] = self.fingers()
        vel = self.block_linvels()
        self.block_acc = (vel - self.prev_block_vel) / self.control_dt
        self.prev_block_vel = vel

    # ----------------------------------------------------------------- sensing
    def contacts(self) -> ContactFlags:
        """Which of the tracked geom pairs touch now."""
        d = self.data
        n = d.ncon
        mask = 0
        if n:
            geoms = d.contact.geom[:n]
            mask = int(np.bitwise_or.reduce(self._contact_bits[geoms[:, 0], geoms[:, 1]]))
        return ContactFlags(**{name: bool(mask >> bit & 1) for bit, name in enumerate(_CONTACT_BITS)})

    def wrist_wrench(self) -> np.ndarray:
        """External contact wrench on the hand + fingers about the TCP, in the TCP frame (what a
        gravity-compensated wrist force-torque sensor reads in quasi-static contact)."""
        d = self.data
        n = d.ncon
        if not n:
            return np.zeros(6)
        contact = d.contact
        on1 = self._gripper_part[contact.geom1[:n]]
        idx = np.flatnonzero(on1 ^ self._gripper_part[contact.geom2[:n]])
        if not idx.size:
            return np.zeros(6)
        local = np.zeros((idx.size, 6))
        for row, i in zip(local, idx.tolist(), strict=True):
            mujoco.mj_contactForce(self.model, d, i, row)
        # contact frame rows are (normal, tangents): world force of geom1 on geom2 = frame^T f
        force = (local[:, None, :3] @ contact.frame[idx].reshape(-1, 3, 3))[:, 0]
        force[on1[idx]] *= -1.0  # the force on the gripper side
        torque = np.cross(contact.pos[idx] - d.site_xpos[self.tcp_site], force)
        rot = d.site_xmat[self.tcp_site].reshape(3, 3)
        return np.concatenate([force.sum(axis=0) @ rot, torque.sum(axis=0) @ rot])

    def observation(self) -> np.ndarray:
        """The 59-dim reference observation (see OBSERVATION_NAMES and docs/panda_play.md)."""
        d = self.data
        tcp = d.site_xpos[self.tcp_site]
        mujoco.mj_objectVelocity(self.model, d, mujoco.mjtObj.mjOBJ_SITE, self.tcp_site, self._vel6, 0)
        pos = d.xpos[self.block_body]
        quat = d.xquat.ravel()[self._block_xyzw_idx].reshape(2, 4)
        quat[quat[:, 3] < 0] *= -1.0  # the reference's w >= 0
        linvel = d.qvel[self._block_linvel_idx].reshape(2, 3)
        # free-joint angular velocity is in the body frame; the reference reports the base frame
        rot = d.xmat[self.block_body].reshape(2, 3, 3)
        angvel = (rot @ d.qvel[self._block_angvel_idx].reshape(2, 3, 1)).reshape(2, 3)
        fingers = self.finger_history
        obs = np.concatenate(
            [
                tcp,
                self._vel6[3:],
                fingers[2],
                fingers[0],
                fingers[1],
                pos[0],
                quat[0],
                pos[1],
                quat[1],
                linvel[0],
                angvel[0],
                linvel[1],
                angvel[1],
                pos[0] - tcp,
                pos[1] - tcp,
                pos[1] - pos[0],
                (BRING_TARGETS - pos).ravel(),
                np.tanh(self.wrist_wrench() * _INV_WRENCH_SCALE),
            ]
        )
        return obs.astype(np.float32)
