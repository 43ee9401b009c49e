"""Door + tactile finger (force-matched imitation, thesis ch. 4): Franka Panda with a single rigid
finger carrying a simulated see-through visuotactile sensor (STS), Cartesian impedance control, a
cabinet door on a self-closing hinge with a flat handle or a spherical knob. Scene and physics in
`physics`, tasks in `tasks`, the gymnasium env in `env`, the scripted expert, the kinesthetic
teacher and plain position replay in `experts` (docs/door_tactile.md)."""

from shiftkit.envs.door_tactile.env import (
    ACTION_NAMES,
    ENVIRONMENT_STATE_INDICES,
    OBSERVATION_NAMES,
    STATE_INDICES,
)
from shiftkit.envs.door_tactile.experts import kinesthetic_rollout, replay_positions, rollout
from shiftkit.envs.door_tactile.physics import SIM_MODEL_ID
from shiftkit.envs.door_tactile.tasks import TASKS
from shiftkit.envs.family import EnvFamily, register_family

FAMILY = register_family(
    EnvFamily(
        name="door-tactile",
        tasks={name: task.gym_name for name, task in TASKS.items()},
        gym_prefix="DoorTactile",
        entry_point="shiftkit.envs.door_tactile.env:DoorTactileEnv",
        robot="franka_panda",
        sim_model_id=SIM_MODEL_ID,
        cameras=("wrist", "front", "sts"),
        observation_names=OBSERVATION_NAMES,
        state_indices=STATE_INDICES,
        environment_state_indices=ENVIRONMENT_STATE_INDICES,
        action_names=ACTION_NAMES,
        observation_layout="state = relative EE pose now + previous, STS wrench estimate, STS mode; "
        "environment_state = door angle, door speed, true pad contact wrench",
        rollout=rollout,
        control_rates=(10,),
        experts={"kinesthetic": kinesthetic_rollout},
    )
)

__all__ = ["FAMILY", "replay_positions"]
