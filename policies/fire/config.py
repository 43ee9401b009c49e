"""The settings of a FIRE run (`shiftkit fire`; defaults: thesis 5.4.2)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shiftkit.datasets.dataclass_config import check_fields, option, option_of
from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.fire.failure_predictors import PREDICTORS
from shiftkit.policies.trainers.bc.args import EARLY_STOP_VAL_FRACTION, BCSettings


@dataclass
class FireBC(BCSettings):
    """BC's settings with the policy of thesis 5.4.2 as defaults (one 2x256 MLP with a tanh output),
    whatever `shiftkit train bc` defaults to; a `FireBC` built in code keeps them too."""

    ensemble_size: int | None = option_of(BCSettings, "ensemble_size", None)
    """BC members (their mean acts, their spread is the doubt); default 1 (thesis 5.4.2), 5 for the
    doubt and gda+doubt predictors (ensemble doubt needs an ensemble)."""
    hidden: list[int] = option_of(BCSettings, "hidden", default_factory=lambda: [256, 256])
    output_activation: str = option_of(BCSettings, "output_activation", "tanh")


@dataclass
class FireArgs:
    """Arguments of `shiftkit fire` (defaults: thesis 5.4.2)."""

    dataset: str
    """Dataset ID or local folder of the initial demonstrations."""
    env: str
    """Registered environment (`shiftkit.envs`) with a scripted expert."""
    task: str
    """Task of the environment."""
    output_dir: str
    """Run folder (config, metrics, checkpoints, policy, episodes)."""
    root: str | None = None
    """Local folder of the dataset (else resolved by ID)."""
    predictor: str = option("gda", choices=tuple(PREDICTORS))
    """Failure predictor: beta, gda, doubt or gda+doubt."""
    budget_expert_samples: int = option(2000, rule="positive_int")
    """Stop once the expert's corrections hold this many samples (the demonstrations not counted)."""
    max_episodes: int | None = option(None, rule="positive_int")
    """Stop after this many episodes at the latest."""
    repo_id: str | None = None
    """Repo ID of the aggregated dataset (default: local/<output folder name>)."""
    dataset_root: str | None = None
    """Where the aggregated dataset is written (default: $HF_LEROBOT_HOME/<repo_id>)."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Environment constructor arguments (control_hz defaults to the dataset's fps)."""
    seed: int = option(0, rule="non_negative_int")
    """Seed of BC, D, sampling and the hold-outs."""
    env_seed: int = option(10_000, rule="non_negative_int")
    """Episode i resets the environment with env_seed + i."""
    expert_policy: str = "scripted"
    """The env's expert that corrects the policy: `scripted` or another of the family's experts that
    acts from any state (panda-play: `suboptimal`, a person's variance), as `shiftkit collect --expert`
    names them; record the demonstrations with the same one."""
    bc: FireBC = field(default_factory=FireBC)
    """The initial BC policy and its training, as `shiftkit train bc` takes them (`--bc.hidden` is
    its `--hidden`), with the policy of thesis 5.4.2 as defaults whatever `train bc` defaults to: one
    2x256 MLP with a tanh output. `val_fraction` is also the share of the demonstrations' episodes
    and of the correction stretches kept for the full retraining's validation (default 0.2 in either
    regime), `batch_size` also the batch per member of the per-episode updates and the retraining."""
    online_lr: float = option(1e-4, rule="positive_float")
    """Learning rate of the per-episode BC updates."""
    retrain_every: int = option(500, rule="positive_int")
    """d: full warm-started BC retraining every this many new expert samples."""
    retrain_lr: float = option(1e-3, rule="positive_float")
    """Learning rate of the full retraining."""
    retrain_max_epochs: int = option(100, rule="positive_int")
    """Most epochs of a full retraining."""
    retrain_patience: int = option(10, rule="positive_int")
    """Epochs without hold-out improvement before a retraining member stops."""
    # --- discriminator and predictors
    d_start: int = option(10_000, rule="non_negative_int")
    """Policy samples before D trains (thesis 5.4.2): until then the policy runs on its own, with no
    prediction, stop, takeover or BC update."""
    d_lr: float = option(1e-3, rule="positive_float")
    """Discriminator learning rate."""
    d_hidden: list[int] = option(default_factory=lambda: [256, 256], rule="positive_int")
    """Discriminator tanh MLP widths."""
    grad_penalty: float = option(10.0, rule="non_negative_float")
    """Discriminator gradient-penalty weight."""
    beta: int = option(20, rule="positive_int")
    """Initial beta of the beta rule."""
    gamma: float = option(0.5, rule="positive_float")
    """Initial posterior threshold of the GDA rule."""
    doubt_threshold: float | None = option(None, rule="positive_float")
    """Initial doubt threshold (default: the largest doubt over the demonstrations' frames)."""
    fp_cooldown: int = option(5, rule="non_negative_int")
    """Steps without predictions after a false positive."""
    expert_margin: int | None = option(None, rule="non_negative_int")
    """Steps the expert needs to finish: the oracle stops an unpredicted failure this many steps
    before the episode's end at the latest (default: the median demonstration's length)."""
    stall_seconds: float = option(2.0, rule="positive_float")
    """The oracle stops an unpredicted failure as soon as it shows: nothing (robot, objects) moved by
    more than `stall_tolerance` for this long while the policy drove."""
    stall_tolerance: float = option(0.02, rule="positive_float")
    """Largest change of any simulator position coordinate (m or rad) that still counts as standing still."""
    # --- evaluation and bookkeeping
    eval_every: int = option(0, rule="non_negative_int")
    """Evaluate the policy every this many episodes (0: never), on seeds from 100000."""
    eval_episodes: int = option(10, rule="positive_int")
    """Episodes per evaluation."""
    device: str = "auto"
    """auto, cpu or cuda."""
    threads: int | None = option(None, rule="positive_int")
    """CPU threads for torch."""
    resume: bool = False
    """Continue the run in output_dir after its last finished episode."""
    progress: bool = False
    """Show a progress bar over the expert budget."""

    def resolved(self) -> FireArgs:
        """A checked copy (each field's rule and choices, then what relates fields); raises ConfigError
        on bad values."""
        check_fields(self)
        if "doubt" in self.predictor and self.bc.ensemble_size == 1:
            raise ConfigError(f"the {self.predictor} predictor needs an ensemble (bc.ensemble_size >= 2) for its doubt")
        if not self.hold_out_share > 0:  # the retrainings validate on it whatever the initial regime
            raise ConfigError(f"bc.val_fraction must be in (0, 1), got {self.bc.val_fraction}")
        if not self.gamma < 1.0:
            raise ConfigError(f"gamma must be in (0, 1), got {self.gamma}")
        from shiftkit.datasets.hub import validate_repo_id

        repo_id = self.repo_id or f"local/{Path(self.output_dir).name}"
        validate_repo_id(repo_id)
        members = self.bc.ensemble_size or (5 if "doubt" in self.predictor else 1)
        bc = dataclasses.replace(self.bc, ensemble_size=members, hidden=list(self.bc.hidden))
        return dataclasses.replace(self, repo_id=repo_id, bc=bc, d_hidden=list(self.d_hidden))

    @property
    def hold_out_share(self) -> float:
        """Share of the demonstrations' episodes (those an early-stop initial BC held out) and of the
        correction stretches kept for the full retraining's validation: the per-episode updates
        never sample them."""
        return EARLY_STOP_VAL_FRACTION if self.bc.val_fraction is None else self.bc.val_fraction


# FIRE's arguments before `FireArgs.bc` held BC's settings flat, under these names
_FLAT_BC = {
    "bc_regime": "regime",
    "bc_steps": "steps",
    "ensemble_size": "ensemble_size",
    "hidden": "hidden",
    "output_activation": "output_activation",
    "val_fraction": "val_fraction",
    "batch_size": "batch_size",
}


def nest_bc_settings(args: dict[str, Any]) -> dict[str, Any]:
    """A FIRE run's stored arguments with BC's settings nested (`bc`), as a run stored them before
    `FireArgs.bc` (such a run resumes); today's arguments unchanged. Its default share of 0.2 becomes
    the unset `bc.val_fraction` that means the same (then an early-stop initial BC held out 0.2, a
    fixed one nothing, as now)."""
    if "bc" in args or "bc_regime" not in args:
        return args
    flat = {new: args[old] for old, new in _FLAT_BC.items() if old in args}
    if flat.get("val_fraction") == EARLY_STOP_VAL_FRACTION:
        flat["val_fraction"] = None
    rest = {k: v for k, v in args.items() if k not in _FLAT_BC}
    return {**rest, "bc": {**dataclasses.asdict(FireBC()), **flat}}


# The rules a failure predictor file holds (`policies/fire/predictor.py`); here so that `fire aggregate
# --help` imports no torch.
RULES = ("beta", "gda")


@dataclass
class AggregateArgs:
    """Arguments of `shiftkit fire aggregate` (D and rule defaults: thesis 5.4.2)."""

    expert: str
    """Dataset ID or local folder of the expert demonstrations."""
    rollouts: list[str]
    """Dataset IDs or local folders of lerobot DAgger recordings (either `record_autonomous` layout)."""
    out: str
    """Folder of the aggregated dataset (must not exist)."""
    repo_id: str
    """Repo ID of the aggregated dataset."""
    root: str | None = None
    """Local folder of the expert dataset (else resolved by ID)."""
    policy: str | None = None
    """BC run folder or checkpoint of the policy that ran the rollouts: D reads its inputs with its
    normalisation (default: every observation feature, the demonstrations' statistics)."""
    predictor: str = option("gda", choices=RULES)
    """Rule whose requests `intervention_request` marks and the predictor file uses: beta or gda."""
    seed: int = option(0, rule="non_negative_int")
    """Seed of D's initialisation and batches."""
    d_steps: int | None = option(None, rule="positive_int")
    """D's gradient steps (default: one per recorded frame)."""
    d_hidden: list[int] = option(default_factory=lambda: [256, 256], rule="positive_int")
    """Discriminator tanh MLP widths."""
    d_lr: float = option(1e-3, rule="positive_float")
    """Discriminator learning rate."""
    grad_penalty: float = option(10.0, rule="non_negative_float")
    """Discriminator gradient-penalty weight."""
    beta: int = option(20, rule="positive_int")
    """Initial beta of the beta rule."""
    gamma: float = option(0.5, rule="positive_float")
    """Initial posterior threshold of the GDA rule."""
    fp_cooldown: int = option(5, rule="non_negative_int")
    """Steps without requests after a refused one."""
    device: str = "auto"
    """auto, cpu or cuda."""
    progress: bool = False
    """Show a progress bar over D's training."""

    def check(self) -> None:
        """ConfigError (one line) for a bad value."""
        check_fields(self)
        from shiftkit.datasets.hub import validate_repo_id

        validate_repo_id(self.repo_id)
        if not self.gamma < 1.0:
            raise ConfigError(f"gamma must be in (0, 1), got {self.gamma}")
