"""Multiview manipulation (thesis ch. 3): a Panda on a mobile base whose SE(2) pose is sampled per
episode (`shiftkit.envs.base_pose`), a base-mounted RGB-D camera, tasks Lift, Stack, PickAndInsert
and Door. One env family per task (`mv-lift`, `mv-stack`, `mv-pick-insert`, `mv-door`), each with
`view="multiview"|"fixed"`. Scene and physics in `physics`, tasks in `tasks`, the gymnasium env in
`env`, scripted experts in `experts`; docs/multiview.md."""

import numpy as np

from shiftkit.envs.base_pose import CAMERA_NAME, SAMPLER
from shiftkit.envs.family import EnvFamily, register_family
from shiftkit.envs.multiview.experts import ExpertPolicy, rollout
from shiftkit.envs.multiview.physics import CONTROL_HZ
from shiftkit.envs.multiview.tasks import STATE_NAMES, TASKS

FAMILIES = {
    task.env: register_family(
        EnvFamily(
            name=task.env,
            tasks={task.name: task.gym_name},
            gym_prefix="Multiview",
            entry_point="shiftkit.envs.multiview.env:MultiviewEnv",
            robot="franka_panda_mobile",
            sim_model_id=task.model_id,
            cameras=(CAMERA_NAME,),
            observation_names=STATE_NAMES + task.environment_names,
            state_indices=np.arange(len(STATE_NAMES)),
            environment_state_indices=np.arange(len(STATE_NAMES), len(STATE_NAMES) + len(task.environment_names)),
            action_names=task.action_names,
            observation_layout="base frame: state = TCP pose + fingers (now, t-1, t-2); environment_state = objects",
            rollout=rollout,
            control_rates=(CONTROL_HZ,),
            expert_policy=ExpertPolicy,
        )
    )
    for task in TASKS.values()
}

__all__ = ["FAMILIES", "SAMPLER", "TASKS"]
