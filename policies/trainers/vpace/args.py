"""The arguments of `shiftkit train vpace|lfgp` (`VPACEArgs`) and the named variants' presets: a module
of their own without torch, so that the command's options are built without importing the trainer
(`training.py`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.errors import ConfigError

VARIANTS: dict[str, dict[str, Any]] = {
    "vpace": dict(reward_model="sqil", multitask=True, value_penalty=10.0, full_trajectories=False),
    "ace": dict(reward_model="sqil", multitask=True, value_penalty=0.0, full_trajectories=False),
    "vp-sqil": dict(reward_model="sqil", multitask=False, value_penalty=10.0, full_trajectories=False),
    "sqil": dict(reward_model="sqil", multitask=False, value_penalty=0.0, full_trajectories=False),
    "dac": dict(reward_model="dac", multitask=False, value_penalty=0.0, full_trajectories=False),
    "rce": dict(reward_model="rce", multitask=False, value_penalty=0.0, full_trajectories=False),
    # LfGP: thesis Table A.2 and the reference code's defaults (utiasSTARS/lfgp `common_args.py`: reward
    # scale 1, no example augmentation), with its shared-trunk network (thesis A.6).
    "lfgp": dict(
        reward_model="dac",
        multitask=True,
        value_penalty=0.0,
        full_trajectories=True,
        shared_trunk=True,
        batch_size=256,
        actor_lr=1e-5,
        polyak=1e-4,
        buffer_warmup=25_000,
        random_steps=50_000,
        expert_sample_rate=0.1,
        expert_sample_decay=0.99999,
        final_pair_bias=0.95,
        reward_scale=1.0,
        aug_factor=0.0,
    ),
}


@dataclass
class VPACEArgs:
    """Arguments of `shiftkit train vpace|lfgp`; defaults are the thesis hyperparameters (docs/vpace.md)."""

    examples: list[str] = field(default_factory=list)
    """Example dataset IDs or local roots; each frame's `task` names the task it is an example of."""
    env: str = "panda-play"
    """Environment name for `shiftkit.envs.make` (or a registered gymnasium id)."""
    main_task: str = ""
    """Task the agent must learn; evaluation runs its intention."""
    aux_tasks: list[str] = field(default_factory=list)
    """Auxiliary tasks (multitask variants only), e.g. reach, grasp, lift, release."""
    output_dir: str = "outputs/vpace"
    """Run directory: config, checkpoints, metrics.jsonl, model card."""
    variant: str = "vpace"
    """Preset of reward_model / multitask / value_penalty / full_trajectories (see module docstring)."""
    reward_model: str = option("sqil", choices=("sqil", "dac", "rce"))
    """sqil | dac | rce."""
    multitask: bool = True
    """Scheduled auxiliary intentions (ACE/LfGP) rather than the main task alone."""
    value_penalty: float = option(10.0, rule="non_negative_float")
    """VP weight lambda; 0 turns value penalization off."""
    full_trajectories: bool = False
    """LfGP: examples are expert trajectories with actions; DAC on (s, a); no per-task example rows in
    the critic (expert transitions enter the batch instead, `expert_sample_rate`)."""
    shared_trunk: bool = False
    """LfGP's network (thesis A.6): policies and Q-functions of every task share one trunk of `hidden`
    layers, with a small head per task; off (VPACE, thesis B.2.6): every network is its own."""
    frames_as_examples: bool = False
    """Use every frame of an `examples` dataset as a success example even if it holds trajectories."""
    examples_per_task: int | None = option(None, rule="positive_int")
    """Use at most this many examples per task (thesis: 200 in simulation); None uses all."""
    aug_factor: float = option(0.1, rule="non_negative_float")
    """Example augmentation: Gaussian noise of this many per-dimension example stds; 0 turns it off."""
    total_steps: int = option(300_000, rule="positive_int")
    """Environment interactions to train for (also the replay capacity)."""
    seed: int = option(0, rule="non_negative_int")
    """Seeds networks, exploration, sampling and environment resets."""
    device: str = "auto"
    """torch device; auto picks cuda when available."""
    torch_threads: int | None = option(None, rule="positive_int")
    """CPU threads for torch (None keeps torch's default); 1 is fastest on a busy or small machine."""
    gamma: float = option(0.99, rule="positive_float")
    """Discount."""
    reward_scale: float = option(0.1, rule="positive_float")
    """Multiplies every reward."""
    batch_size: int = option(128, rule="positive_int")
    """Replay rows per update, shared by all intentions (LfGP: expert transitions take the place of a
    share of them); also the discriminator's rows per task."""
    example_batch_size: int = option(128, rule="positive_int")
    """Example rows per update for the critics, divided among the tasks (rows // tasks each, the main
    task the remainder), as the reference code's `fraction` sampling does."""
    expert_sample_rate: float = option(0.0, rule="non_negative_float")
    """Full trajectories: share of the batch that is expert transitions (thesis Table A.2 "BE sampling
    proportion", 0.1), divided among the tasks, for critics and policies of every task."""
    expert_sample_decay: float = option(1.0, rule="positive_float")
    """Factor on `expert_sample_rate` per update (Table A.2: 0.99999)."""
    final_pair_bias: float = option(0.0, rule="non_negative_float")
    """Share of the discriminator's expert rows drawn from rows that end a demonstration, the (s_T, 0)
    pairs and segments' last rows (Table A.2 "(s_T, 0) sampling bias", 0.95)."""
    lr: float = option(3e-4, rule="positive_float")
    """Adam(W) learning rate of critics, discriminators and temperatures."""
    actor_lr: float = option(3e-4, rule="positive_float")
    """AdamW learning rate of the policies (LfGP, Table A.2: 1e-5)."""
    weight_decay: float = option(1e-2, rule="non_negative_float")
    """Decoupled (AdamW) weight decay of policies, critics and discriminators. Adam's coupled L2 form must
    not be used here: where a critic's data gradients are small, Adam normalises the decay term itself to
    steps of size lr and shrinks the whole network to zero within a few thousand updates."""
    initial_alpha: float = option(1e-2, rule="positive_float")
    """Initial SAC temperature of every intention (target entropy is -dim(action))."""
    polyak: float = option(1e-3, rule="positive_float")
    """Target critic averaging rate (LfGP, Table A.2: 1e-4)."""
    max_grad_norm: float = option(10.0, rule="positive_float")
    """Gradient norm clip of the policies, of the critics and of the temperatures, each one norm over
    every task's parameters (as the reference code clips)."""
    buffer_warmup: int = option(5_000, rule="non_negative_int")
    """Interactions before the first update."""
    random_steps: int = option(10_000, rule="non_negative_int")
    """Interactions with uniform random actions at the start."""
    n_step: int = option(1, rule="positive_int")
    """n-step returns for buffer rows (1: plain TD)."""
    hidden: tuple[int, ...] = option((256, 256), rule="positive_int")
    """Hidden layer widths of every network."""
    vp_filter_size: int = option(50, rule="positive_int")
    """Median filter length for Q_max (and a learned reward's minimum)."""
    vp_q_max: str = option("mean", choices=("mean", "max"))
    """How Q_max is read from the example batch's Q(s*, a*): mean (thesis) or max (the reference code's
    other choice, a looser bound)."""
    gradient_penalty: float = option(10.0, rule="non_negative_float")
    """DAC discriminator gradient penalty weight."""
    num_periods: int = option(8, rule="positive_int")
    """Scheduler periods per episode (8 Panda, 5 others)."""
    main_rate: float = option(0.5, rule="non_negative_float")
    """Weighted random scheduler probability of the main task."""
    handcraft_rate: float = option(0.5, rule="non_negative_float")
    """Probability that an episode follows a handcrafted sequence (when any are given)."""
    handcrafted: list[str] = field(default_factory=list)
    """Handcrafted sequences, comma-separated task names per period (`main` = main task), or the name of
    one of the thesis' sets: panda (VPACE), panda-lfgp (LfGP), reach-grasp (Sawyer/Adroit)."""
    scheduler: str = option("wrs", choices=("wrs", "learned"))
    """wrs (weighted random + handcrafted) or learned (SAC-Q's Q-table over task histories, scored by the
    main task's learned reward; needs the dac reward model)."""
    episode_steps: int | None = option(None, rule="positive_int")
    """Episode length; None takes the environment's time limit."""
    eval_every: int = option(25_000, rule="non_negative_int")
    """Evaluate the main intention every this many interactions (0: never)."""
    eval_episodes: int = option(50, rule="positive_int")
    """Episodes per evaluation."""
    checkpoint_every: int = option(25_000, rule="positive_int")
    """Write a checkpoint at the first episode end after every this many interactions."""
    log_every: int = option(1_000, rule="positive_int")
    """Write training metrics every this many interactions."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for the environment constructor."""
    resume: bool = False
    """Continue the run in output_dir from its newest checkpoint."""

    @classmethod
    def for_variant(cls, variant: str, **overrides: Any) -> VPACEArgs:
        """The args of a named variant (VARIANTS), with `overrides` on top."""
        if variant not in VARIANTS:
            raise ConfigError(f"unknown variant {variant!r}; choose from {', '.join(VARIANTS)}")
        return cls(variant=variant, **(VARIANTS[variant] | overrides))

    def validate(self) -> None:
        """Raises ConfigError naming the first invalid or inconsistent setting."""
        check_fields(self)
        if not self.main_task:
            raise ConfigError("--main-task is required")
        if self.reward_model == "rce" and self.value_penalty > 0:
            raise ConfigError("RCE's classifier critic is bounded already; value penalty must be 0 with rce")
        if not 0.0 <= self.expert_sample_rate <= 1.0 or not 0.0 <= self.final_pair_bias <= 1.0:
            raise ConfigError("expert_sample_rate and final_pair_bias must lie in [0, 1]")
        if not 0.0 < self.expert_sample_decay <= 1.0:
            raise ConfigError("expert_sample_decay must lie in (0, 1]")
        if self.expert_sample_rate > 0 and not self.full_trajectories:
            raise ConfigError("expert transitions in the batch (expert_sample_rate) need full trajectories (lfgp)")
        if self.full_trajectories and self.reward_model != "dac":
            raise ConfigError("full trajectories (lfgp) need the dac reward model")
        if (self.full_trajectories or self.reward_model == "rce") and self.n_step != 1:
            raise ConfigError("n-step returns are only supported with state-only sqil/dac rewards; use n_step 1")
        if self.scheduler == "learned" and not (self.multitask and self.reward_model == "dac"):
            raise ConfigError(
                "the learned scheduler needs several tasks and a learned reward (dac): it scores "
                "plans by the main task's reward, which SQIL/RCE do not provide"
            )
        if self.multitask and self.main_task in self.aux_tasks:
            raise ConfigError(f"main task {self.main_task!r} is also listed as an auxiliary task")

    @property
    def tasks(self) -> list[str]:
        """The tasks trained, main first (only the main task when not multitask)."""
        return [self.main_task, *self.aux_tasks] if self.multitask else [self.main_task]
