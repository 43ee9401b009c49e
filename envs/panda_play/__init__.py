"""Panda play (LfGP / VPACE, thesis ch. 6-7): Franka Panda, a tray with two blocks, bring zones and
insertion slots; reset-based tasks and play episodes. Scene and physics in `physics`, task
predicates in `tasks`, the gymnasium env in `env`, scripted experts in `experts`, the published
VPACE data's conventions in `vpace_compat`."""

from shiftkit.envs.family import EnvFamily, register_family
from shiftkit.envs.panda_play.experts import (
    PLAY_SEQUENCES,
    ExpertPolicy,
    SuboptimalExpertPolicy,
    play_rollout,
    rollout,
    suboptimal_rollout,
)
from shiftkit.envs.panda_play.physics import (
    ACTION_NAMES,
    CAMERAS,
    ENVIRONMENT_STATE_INDICES,
    OBSERVATION_NAMES,
    SIM_MODEL_ID,
    STATE_INDICES,
)
from shiftkit.envs.panda_play.tasks import TASKS
from shiftkit.envs.panda_play.vpace_compat import vpace_action_to_shiftkit

FAMILY = register_family(
    EnvFamily(
        name="panda-play",
        tasks={name: task.gym_name for name, task in TASKS.items()},
        gym_prefix="PandaPlay",
        entry_point="shiftkit.envs.panda_play.env:PandaPlayEnv",
        robot="franka_panda",
        sim_model_id=SIM_MODEL_ID,
        cameras=tuple(CAMERAS),
        observation_names=OBSERVATION_NAMES,
        state_indices=STATE_INDICES,
        environment_state_indices=ENVIRONMENT_STATE_INDICES,
        action_names=ACTION_NAMES,
        observation_layout="reference 59-dim = state[:12] + environment_state + state[12:]",
        rollout=rollout,
        control_rates=(20, 5),
        play_rollout=play_rollout,
        play_sequences=PLAY_SEQUENCES,
        action_conventions={"vpace": vpace_action_to_shiftkit},
        expert_policy=ExpertPolicy,
        experts={"suboptimal": suboptimal_rollout},
        expert_policies={"suboptimal": SuboptimalExpertPolicy},
    )
)
