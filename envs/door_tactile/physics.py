"""Door + tactile finger scene: composition with `mujoco.MjSpec`, Cartesian impedance control, the
self-closing door hinge and the contact facts the sensor and the tasks read.

Physics only, no task logic (tasks live in `tasks`). Everything is in the robot base frame, which
is the MuJoCo world frame (base at the origin, z up):

* the gymnasium-robotics Franka Panda (`shiftkit.envs.panda_model`) with its gripper replaced by a
  single rigid finger (a 9 cm box along the flange axis); on the finger's side near the tip sits the
  STS pad, a soft (gel-like) box whose outward normal is the sensor's z axis. The `ee` site is the
  sensor frame: z = pad normal, x = along the finger towards the tip;
* a wall cabinet whose door (40 x 50 cm, bottom at z = 0.50) hangs on a vertical hinge at
  x = -0.30, y = 0.68 (where the Panda reaches it with the finger level); opening
  (positive angle) swings the free edge towards the robot. The hinge is self-closing: below
  `SPRING_ENGAGE` rad a spring pulls the door shut (1 Nm at the stop), above it dry hinge friction
  holds the door where it is (a cabinet self-closing hinge);
* a flat metal handle (a 6 mm fin standing out 4 cm from the door) or a spherical glass knob
  (1.8 cm radius on a 2.5 cm stem), 5 cm from the free edge at z = 0.75. A single finger opens or
  closes the door by pressing the pad against the hinge side of the handle and dragging it along the
  door's arc: the pull is transmitted by friction, so it needs a pressing force (thesis §4.1,
  "press and pull"; fig. 4.2b).

Control: joint torques from `controllers.CartesianImpedance` (550 N/m, 30 Nm/rad, near-critical
damping, null-space posture) every 2 ms physics step; gravity is compensated by the model
(`gravcomp`). Freedrive (kinesthetic teaching) sets the stiffness to zero and applies the teacher's
wrench at the finger.
"""

from __future__ import annotations

import mujoco
import numpy as np

from shiftkit.envs.cameras import look_at
from shiftkit.envs.controllers import CartesianImpedance
from shiftkit.envs.geometry import quat_wxyz, rotation_vector, rotation_z
from shiftkit.envs.panda_model import panda_spec
from shiftkit.envs.scene import SCENE_GROUP, add_box, add_light_and_ground

SIM_MODEL_ID = "door-tactile-v1"
VARIANTS = ("flat", "knob")

PHYSICS_DT = 0.002
# impedance gains (thesis §4.4.1: Polymetis default Cartesian impedance on a Franka Panda)
STIFFNESS = (550.0, 30.0)
TORQUE_LIMIT = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
# the kitchen model's joint damping (100 Nms/rad on the shoulder) would swamp the impedance law
ARM_JOINT_DAMPING = 0.5
ARM_ARMATURE = 0.1
# freedrive: the arm is only damped (per unit of task-space inertia, 1/s), as a Panda in guiding mode
FREEDRIVE_DAMPING = 6.0

# door and hinge
HINGE_XY = np.array([-0.30, 0.68])
DOOR_WIDTH, DOOR_HEIGHT, DOOR_THICK = 0.40, 0.50, 0.02
DOOR_BOTTOM = 0.50
DOOR_MASS = 2.0
HANDLE_FROM_EDGE = 0.05
HANDLE_Z = 0.75
HANDLE_RADIUS = DOOR_WIDTH - HANDLE_FROM_EDGE  # lever arm about the hinge
FIN_HALF = (0.003, 0.02, 0.05)  # flat handle: thickness (along the door), stand-off, height
KNOB_RADIUS, KNOB_STEM = 0.018, 0.025
SPRING_ENGAGE = 0.5  # rad: the self-closing spring acts below this angle
SPRING_STIFFNESS = 2.0  # Nm/rad: 1 Nm at the closed stop (about 3 N at the handle)
HINGE_FRICTION = 0.15  # Nm dry friction: holds an open door above SPRING_ENGAGE
HINGE_DAMPING = 0.02
DOOR_MAX_ANGLE = 1.7
HANDLE_FRICTION = {"flat": 0.9, "knob": 0.7}  # metal fin vs glass knob against the gel

# finger and STS pad, in the link7 frame (z along the flange)
FINGER_BASE = 0.16
FINGER_HALF = (0.012, 0.012, 0.045)
PAD_HALF = (0.003, 0.011, 0.014)  # pad thickness along link7 x, width, length
PAD_CENTER_Z = 0.073  # from the finger base: the pad ends 0.8 cm before the tip
PAD_SOLREF = (0.02, 1.0)
# soft gel: 1.7 mm deep at 0.4 N, 2.7 mm at 4 N, 3.2 mm at 9 N (impedance rising over 8 mm)
PAD_SOLIMP = (0.01, 0.9, 0.008, 0.5, 2.0)
PAD_FRICTION = 0.5  # below the handles': MuJoCo takes the larger of a pair, so the handle's counts
# sensor frame in link7 axes: x along the finger, z the pad normal (link7 x), y = z cross x
SENSOR_AXES = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])

# sensor frame orientation at yaw 0 (world): pad normal +x, finger +y, sensor y = world z
EE_ROTATION = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# a posture near the handle (IK solutions along the opening arc lie close to it)
HOME_QPOS = np.array([0.8, -0.6, 0.6, -2.2, 0.0, 1.65, 1.1])

CAMERAS = {
    "wrist": None,  # on link7, looking along the finger
    "sts": None,  # inside the sensor, looking out through the pad (visual mode)
    "front": dict(pos=(0.55, -0.25, 0.75), target=(-0.05, 0.45, 0.35), fovy=55.0),
}


def door_handle_local(variant: str) -> np.ndarray:
    """Handle (fin centre / knob centre) in the door body frame."""
    stand_off = FIN_HALF[1] if variant == "flat" else KNOB_STEM + KNOB_RADIUS
    return np.array([HANDLE_RADIUS, -DOOR_THICK / 2 - stand_off, HANDLE_Z - DOOR_BOTTOM - DOOR_HEIGHT / 2])


def build_spec(variant: str) -> mujoco.MjSpec:
    """Compose the scene: Panda with the STS finger + cabinet door with the given handle."""
    if variant not in VARIANTS:
        raise ValueError(f"door variant must be one of {VARIANTS}, got {variant!r}")
    # stiff friction: without it the soft gel contact creeps along the handle far inside the friction
    # cone (measured: 2.5 cm of creep over 10 s at impratio 5, 2 mm at 100)
    spec = panda_spec(SIM_MODEL_ID, timestep=PHYSICS_DT, impratio=100.0)
    # the STS camera sees a handle a few millimetres away: near plane at 0.1% of the model extent
    spec.visual.map.znear = 0.001
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]

    for name in ("panda0_leftfinger", "panda0_rightfinger"):
        spec.delete(spec.body(name))
    for act in list(spec.actuators):
        if "finger" in act.name:
            spec.delete(act)
    for i, act in enumerate(spec.actuators):
        act.set_to_motor()
        act.ctrlrange = [-TORQUE_LIMIT[i], TORQUE_LIMIT[i]]
        act.ctrllimited = True
        act.forcerange = [-TORQUE_LIMIT[i], TORQUE_LIMIT[i]]
    for body in spec.bodies:
        if body.name.startswith("panda0_"):
            body.gravcomp = 1.0
    for joint in spec.joints:
        if joint.name.startswith("robot:panda0_joint"):
            joint.damping = [ARM_JOINT_DAMPING, 0.0, 0.0]
            joint.armature = ARM_ARMATURE
    for geom in spec.geoms:
        # only the hand and the finger collide (the arm stays clear of the cabinet)
        if geom.group == 3 and geom.parent.name != "panda0_link7":
            geom.contype = geom.conaffinity = 0

    link7 = spec.body("panda0_link7")
    finger = link7.add_body()
    finger.name = "sts_finger"
    finger.pos = [0.0, 0.0, FINGER_BASE]
    finger.gravcomp = 1.0
    g = add_box(finger, "finger", FINGER_HALF, (0, 0, FINGER_HALF[2]), (0.25, 0.25, 0.28, 1.0), group=3)
    g.mass = 0.15
    # the same box for the full-quality view
    add_box(finger, "finger_visual", FINGER_HALF, (0, 0, FINGER_HALF[2]), (0.25, 0.25, 0.28, 1.0), 0, False)
    pad_x = FINGER_HALF[0] + PAD_HALF[0]
    for group, name in ((3, "sts_pad"), (0, "sts_pad_visual")):
        pad = add_box(finger, name, PAD_HALF, (pad_x, 0, PAD_CENTER_Z), (0.85, 0.85, 0.8, 1.0), group, group == 3)
        pad.mass = 0.01
        if group == 3:
            pad.solref = list(PAD_SOLREF)
            pad.solimp = list(PAD_SOLIMP)
            pad.friction = [PAD_FRICTION, 0.005, 0.0001]
            pad.condim = 6
            pad.solmix = 1000.0  # the gel's softness dominates a pair; friction is the pair's larger
    site = finger.add_site()
    site.name = "ee"
    site.pos = [pad_x + PAD_HALF[0], 0.0, PAD_CENTER_Z]
    site.quat = quat_wxyz(SENSOR_AXES.T).tolist()
    site.size = [0.004, 0.004, 0.004]
    site.group = 5
    sts = finger.add_camera()
    sts.name = "sts"
    # behind the gel looking out along the pad normal (MuJoCo cameras look along -z)
    sts.pos = [FINGER_HALF[0] - 0.002, 0.0, PAD_CENTER_Z]
    sts.quat = quat_wxyz(np.column_stack([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])).tolist()
    sts.fovy = 90.0
    wrist = link7.add_camera()
    wrist.name = "wrist"
    # above the flange, looking along the finger past the pad side
    wrist.pos = [0.06, 0.0, 0.10]
    wrist.quat = quat_wxyz(np.column_stack([[0.0, 1.0, 0.0], [-0.8, 0.0, -0.6], [0.6, 0.0, -0.8]])).tolist()
    wrist.fovy = 70.0

    world = spec.worldbody
    add_light_and_ground(world, [0.0, 0.0, 1.5], [0.0, 0.3, -1.0])

    # cabinet carcass behind the door plane: seen, not collided with (the hinge range is the door stop)
    cabinet = world.add_body()
    cabinet.name = "cabinet"
    cabinet.pos = [HINGE_XY[0] + DOOR_WIDTH / 2, HINGE_XY[1] + 0.2, DOOR_BOTTOM + DOOR_HEIGHT / 2]
    wood = (0.55, 0.42, 0.3, 1.0)
    w, h, t = DOOR_WIDTH / 2 + 0.02, DOOR_HEIGHT / 2 + 0.02, 0.01
    add_box(cabinet, "cabinet_back", (w, t, h), (0, 0.19, 0), wood, collide=False)
    add_box(cabinet, "cabinet_left", (t, 0.2, h), (-w, 0, 0), wood, collide=False)
    add_box(cabinet, "cabinet_right", (t, 0.2, h), (w, 0, 0), wood, collide=False)
    add_box(cabinet, "cabinet_top", (w, 0.2, t), (0, 0, h), wood, collide=False)
    add_box(cabinet, "cabinet_bottom", (w, 0.2, t), (0, 0, -h), wood, collide=False)
    add_box(cabinet, "cabinet_shelf", (w - t, 0.18, 0.005), (0, 0.01, 0), (0.6, 0.5, 0.4, 1.0), collide=False)

    door = world.add_body()
    door.name = "door"
    door.pos = [HINGE_XY[0], HINGE_XY[1], DOOR_BOTTOM + DOOR_HEIGHT / 2]
    hinge = door.add_joint()
    hinge.name = "door_hinge"
    hinge.type = mujoco.mjtJoint.mjJNT_HINGE
    hinge.axis = [0.0, 0.0, -1.0]  # positive = free edge towards the robot
    hinge.range = [0.0, DOOR_MAX_ANGLE]
    hinge.limited = True
    hinge.frictionloss = HINGE_FRICTION
    hinge.damping = [HINGE_DAMPING, 0.0, 0.0]
    panel = add_box(door, "door_panel", (DOOR_WIDTH / 2, DOOR_THICK / 2, DOOR_HEIGHT / 2), (DOOR_WIDTH / 2, 0, 0), wood)
    panel.mass = DOOR_MASS
    handle = door_handle_local(variant)
    metal = (0.75, 0.75, 0.78, 1.0)
    if variant == "flat":
        g = add_box(door, "handle", FIN_HALF, handle, metal)
    else:
        stem = door.add_geom()
        stem.name = "knob_stem"
        stem.type = mujoco.mjtGeom.mjGEOM_CYLINDER
        stem.size = [0.006, KNOB_STEM / 2, 0.0]
        stem.pos = [handle[0], -DOOR_THICK / 2 - KNOB_STEM / 2, handle[2]]
        stem.quat = [0.7071068, 0.7071068, 0.0, 0.0]
        stem.rgba = list(metal)
        stem.group = SCENE_GROUP
        g = door.add_geom()
        g.name = "handle"
        g.type = mujoco.mjtGeom.mjGEOM_SPHERE
        g.size = [KNOB_RADIUS, 0.0, 0.0]
        g.pos = list(handle)
        g.rgba = [0.7, 0.85, 0.9, 1.0]
        g.group = SCENE_GROUP
    g.mass = 0.1
    g.friction = [HANDLE_FRICTION[variant], 0.005, 0.0001]
    g.condim = 6

    cam = CAMERAS["front"]
    front = world.add_camera()
    front.name = "front"
    front.pos = list(cam["pos"])
    front.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    front.alt.xyaxes = list(look_at(cam["pos"], cam["target"]))
    front.fovy = cam["fovy"]
    return spec


class DoorTactilePhysics:
    """Model/data of the door scene, the impedance controller, the hinge spring and contact facts."""

    def __init__(self, variant: str, control_hz: int = 10) -> None:
        self.variant = variant
        self.model = build_spec(variant).compile()
        self.data = mujoco.MjData(self.model)
        self.control_hz = control_hz
        self.n_substeps = int(round(1.0 / (control_hz * PHYSICS_DT)))
        m = self.model
        self.ee_site = m.site("ee").id
        arm = [m.joint(f"robot:panda0_joint{i}") for i in range(1, 8)]
        qadr, vadr = arm[0].qposadr[0], arm[0].dofadr[0]
        self.arm_qpos = slice(qadr, qadr + 7)
        self.arm_dofs = slice(vadr, vadr + 7)
        self.arm_joint_ids = np.array([j.id for j in arm])
        hinge = m.joint("door_hinge")
        self.door_qpos, self.door_dof = int(hinge.qposadr[0]), int(hinge.dofadr[0])
        self.pad_geom = m.geom("sts_pad").id
        self.handle_geom = m.geom("handle").id
        self.finger_body = m.body("sts_finger").id
        self.controller = CartesianImpedance(m, self.ee_site, self.arm_qpos, self.arm_dofs, HOME_QPOS, TORQUE_LIMIT)
        self.target_pos = np.zeros(3)
        self.target_rot = EE_ROTATION.copy()

    # ----------------------------------------------------------------- state access
    def ee_pos(self) -> np.ndarray:
        """Sensor site position (3,), world frame (m)."""
        return self.data.site_xpos[self.ee_site].copy()

    def ee_rot(self) -> np.ndarray:
        """Sensor site rotation (3, 3), world frame."""
        return self.data.site_xmat[self.ee_site].reshape(3, 3).copy()

    def door_angle(self) -> float:
        """Door hinge angle (rad)."""
        return float(self.data.qpos[self.door_qpos])

    def door_velocity(self) -> float:
        """Door hinge velocity (rad/s)."""
        return float(self.data.qvel[self.door_dof])

    # ----------------------------------------------------------------- reset
    def reset(self, ee_pos: np.ndarray, ee_rot: np.ndarray, door_angle: float) -> None:
        """Place the sensor at (`ee_pos`, `ee_rot`) by IK and the door at `door_angle`, at rest."""
        d = self.data
        mujoco.mj_resetData(self.model, d)
        d.qpos[self.arm_qpos] = HOME_QPOS
        d.qpos[self.door_qpos] = door_angle
        self._solve_ik(ee_pos, ee_rot)
        self.controller.home = d.qpos[self.arm_qpos].copy()
        self.target_pos, self.target_rot = np.asarray(ee_pos, float).copy(), np.asarray(ee_rot, float).copy()
        mujoco.mj_forward(self.model, d)

    def _solve_ik(self, pos: np.ndarray, rot: np.ndarray, iterations: int = 300) -> None:
        """Damped least-squares IK of the sensor pose on `data` (kinematics only)."""
        m, d = self.model, self.data
        jac = np.zeros((6, m.nv))
        for _ in range(iterations):
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            cur = d.site_xmat[self.ee_site].reshape(3, 3)
            err = np.concatenate((pos - d.site_xpos[self.ee_site], rotation_vector(rot @ cur.T)))
            if np.linalg.norm(err) < 1e-6:
                break
            mujoco.mj_jacSite(m, d, jac[:3], jac[3:], self.ee_site)
            j = jac[:, self.arm_dofs]
            dq = j.T @ np.linalg.solve(j @ j.T + 1e-4 * np.eye(6), err)
            dq += 0.1 * (np.eye(7) - np.linalg.pinv(j) @ j) @ (HOME_QPOS - d.qpos[self.arm_qpos])
            dq = dq.clip(-0.1, 0.1)
            d.qpos[self.arm_qpos] = (d.qpos[self.arm_qpos] + dq).clip(*self.model.jnt_range[self.arm_joint_ids].T)

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """Restore a simulator state; the controller then holds the sensor where it is."""
        self.data.qpos[:] = qpos
        self.data.qvel[:] = qvel
        mujoco.mj_forward(self.model, self.data)
        self.target_pos, self.target_rot = self.ee_pos(), self.ee_rot()

    # ----------------------------------------------------------------- control
    def spring_torque(self) -> float:
        """Self-closing hinge torque (along the opening axis): pulls the door shut below SPRING_ENGAGE."""
        return -SPRING_STIFFNESS * max(0.0, SPRING_ENGAGE - self.door_angle())

    def simulate(self, n: int, stiffness_scale: float = 1.0, teacher=None) -> float:
        """Advance `n` physics steps under the impedance law towards the current target (scaled
        stiffness; 0 = freedrive). `teacher(self)`, if given, returns before every step a world-frame
        wrench (6,) applied at the sensor (a person's hand on the finger) and may move the target.
        Returns the fastest closing speed of the door (rad/s) seen while the finger was off the
        handle (what a slam looks like)."""
        m, d = self.model, self.data
        free_closing = 0.0
        for _ in range(n):
            mujoco.mj_step1(m, d)
            wrench = teacher(self) if teacher is not None else None
            d.ctrl[:7] = self.controller.torque(
                d,
                self.target_pos,
                self.target_rot,
                stiffness_scale,
                min_damping=0.0 if stiffness_scale else FREEDRIVE_DAMPING,
            )
            d.qfrc_applied[:] = 0.0
            d.qfrc_applied[self.door_dof] = self.spring_torque()
            if wrench is not None:
                mujoco.mj_applyFT(
                    m, d, wrench[:3], wrench[3:], d.site_xpos[self.ee_site], self.finger_body, d.qfrc_applied
                )
            mujoco.mj_step2(m, d)
            closing = -d.qvel[self.door_dof]
            if closing > free_closing and closing > 0.2 and not self.handle_contact():
                free_closing = float(closing)
        mujoco.mj_forward(m, d)
        return free_closing

    # ----------------------------------------------------------------- contacts
    def handle_contact(self) -> bool:
        """Whether the finger (pad or housing) touches the handle/knob."""
        d = self.data
        n = d.ncon
        g1, g2 = d.contact.geom1[:n], d.contact.geom2[:n]
        body = self.model.geom_bodyid
        return bool(
            np.any((g1 == self.handle_geom) & (body[g2] == self.finger_body))
            or np.any((g2 == self.handle_geom) & (body[g1] == self.finger_body))
        )

    def grasp_pose(self, door_angle: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Sensor pose touching the hinge side of the handle (pad centre on the fin face / knob
        equator, pad normal along the door towards the free edge) at `door_angle` (default: now)."""
        angle = self.door_angle() if door_angle is None else door_angle
        rot = rotation_z(-angle)  # the hinge turns about -z
        local = door_handle_local(self.variant) - [FIN_HALF[0] if self.variant == "flat" else KNOB_RADIUS, 0.0, 0.0]
        origin = np.array([*HINGE_XY, DOOR_BOTTOM + DOOR_HEIGHT / 2])
        return origin + rot @ local, rot @ EE_ROTATION

    def door_outward(self, door_angle: float | None = None) -> np.ndarray:
        """Unit normal of the door's front face (towards the robot when closed)."""
        angle = self.door_angle() if door_angle is None else door_angle
        return rotation_z(-angle) @ np.array([0.0, -1.0, 0.0])
