"""The settings of a FIRE run (`shiftkit fire`; defaults: thesis 5.4.2)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shiftkit.datasets.errors import ConfigError, require_positive
from shiftkit.policies.fire.failure_predictors import PREDICTORS
from shiftkit.policies.trainers.bc.args import OUTPUT_ACTIVATIONS


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
    predictor: str = "gda"
    """Failure predictor: beta, gda, doubt or gda+doubt."""
    budget_expert_samples: int = 2000
    """Stop once the expert's corrections hold this many samples (the demonstrations not counted)."""
    max_episodes: int | None = None
    """Stop after this many episodes at the latest."""
    repo_id: str | None = None
    """Repo ID of the aggregated dataset (default: local/<output folder name>)."""
    dataset_root: str | None = None
    """Where the aggregated dataset is written (default: $HF_LEROBOT_HOME/<repo_id>)."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Environment constructor arguments (control_hz defaults to the dataset's fps)."""
    seed: int = 0
    """Seed of BC, D, sampling and the hold-outs."""
    env_seed: int = 10_000
    """Episode i resets the environment with env_seed + i."""
    expert_policy: str = "scripted"
    """The env's expert that corrects the policy: `scripted` or another of the family's experts that
    acts from any state (panda-play: `suboptimal`, a person's variance), as `shiftkit collect --expert`
    names them; record the demonstrations with the same one."""
    # --- BC (the policy of thesis 5.4.2: one 2x256 MLP, tanh output; FIRE's own settings, whatever
    # `shiftkit train bc` defaults to)
    bc_regime: str = "early-stop"
    """Initial BC regime (`shiftkit train bc --regime`)."""
    bc_steps: int | None = None
    """Initial BC steps (fixed regime; a bound for early-stop)."""
    ensemble_size: int | None = None
    """BC members (their mean acts, their spread is the doubt); default 1 (thesis 5.4.2), 5 for the
    doubt and gda+doubt predictors (ensemble doubt needs an ensemble)."""
    hidden: list[int] = field(default_factory=lambda: [256, 256])
    """BC hidden widths."""
    output_activation: str = "tanh"
    """BC output: `tanh` (actions bounded to [-1, 1], thesis 5.4.2) or `linear`."""
    val_fraction: float = 0.2
    """Share of the demonstrations' episodes (those the initial early-stop BC held out) and of the
    correction stretches kept for the full retraining's validation: the per-episode updates never
    sample them."""
    batch_size: int = 64
    """BC batch per member (initial training, updates, retraining)."""
    online_lr: float = 1e-4
    """Learning rate of the per-episode BC updates."""
    retrain_every: int = 500
    """d: full warm-started BC retraining every this many new expert samples."""
    retrain_lr: float = 1e-3
    """Learning rate of the full retraining."""
    retrain_max_epochs: int = 100
    """Most epochs of a full retraining."""
    retrain_patience: int = 10
    """Epochs without hold-out improvement before a retraining member stops."""
    # --- discriminator and predictors
    d_start: int = 10_000
    """Policy samples before D trains (thesis 5.4.2): until then the policy runs on its own, with no
    prediction, stop, takeover or BC update."""
    d_lr: float = 1e-3
    """Discriminator learning rate."""
    d_hidden: list[int] = field(default_factory=lambda: [256, 256])
    """Discriminator tanh MLP widths."""
    grad_penalty: float = 10.0
    """Discriminator gradient-penalty weight."""
    beta: int = 20
    """Initial beta of the beta rule."""
    gamma: float = 0.5
    """Initial posterior threshold of the GDA rule."""
    doubt_threshold: float | None = None
    """Initial doubt threshold (default: the largest doubt over the demonstrations' frames)."""
    fp_cooldown: int = 5
    """Steps without predictions after a false positive."""
    expert_margin: int | None = None
    """Steps the expert needs to finish: the oracle stops an unpredicted failure this many steps
    before the episode's end at the latest (default: the median demonstration's length)."""
    stall_seconds: float = 2.0
    """The oracle stops an unpredicted failure as soon as it shows: nothing (robot, objects) moved by
    more than `stall_tolerance` for this long while the policy drove."""
    stall_tolerance: float = 0.02
    """Largest change of any simulator position coordinate (m or rad) that still counts as standing still."""
    # --- evaluation and bookkeeping
    eval_every: int = 0
    """Evaluate the policy every this many episodes (0: never), on seeds from 100000."""
    eval_episodes: int = 10
    """Episodes per evaluation."""
    device: str = "auto"
    """auto, cpu or cuda."""
    threads: int | None = None
    """CPU threads for torch."""
    resume: bool = False
    """Continue the run in output_dir after its last finished episode."""
    progress: bool = False
    """Show a progress bar over the expert budget."""

    def resolved(self) -> FireArgs:
        """A checked copy; raises ConfigError on bad values."""
        if self.predictor not in PREDICTORS:
            raise ConfigError(f"unknown predictor {self.predictor!r} (choose from {', '.join(PREDICTORS)})")
        require_positive(
            self,
            "budget_expert_samples",
            "batch_size",
            "retrain_every",
            "retrain_max_epochs",
            "retrain_patience",
            "beta",
            "eval_episodes",
            "online_lr",
            "retrain_lr",
            "d_lr",
            "stall_seconds",
            "stall_tolerance",
        )
        require_positive(self, "d_start", "fp_cooldown", "eval_every", "grad_penalty", allow_zero=True)
        if self.ensemble_size is not None and self.ensemble_size <= 0:
            raise ConfigError(f"ensemble_size must be positive, got {self.ensemble_size}")
        if "doubt" in self.predictor and self.ensemble_size == 1:
            raise ConfigError(f"the {self.predictor} predictor needs an ensemble (ensemble_size >= 2) for its doubt")
        if not 0.0 < self.val_fraction < 1.0:
            raise ConfigError(f"val_fraction must be in (0, 1), got {self.val_fraction}")
        if self.output_activation not in OUTPUT_ACTIVATIONS:
            raise ConfigError(
                f"unknown output activation {self.output_activation!r} (choose from {', '.join(OUTPUT_ACTIVATIONS)})"
            )
        if self.max_episodes is not None and self.max_episodes <= 0:
            raise ConfigError(f"max_episodes must be positive, got {self.max_episodes}")
        if not 0.0 < self.gamma < 1.0:
            raise ConfigError(f"gamma must be in (0, 1), got {self.gamma}")
        if self.doubt_threshold is not None and not self.doubt_threshold > 0:
            raise ConfigError(f"doubt_threshold must be positive, got {self.doubt_threshold}")
        if self.expert_margin is not None and self.expert_margin < 0:
            raise ConfigError(f"expert_margin must be >= 0, got {self.expert_margin}")
        if any(h <= 0 for h in [*self.hidden, *self.d_hidden]):
            raise ConfigError("hidden widths must be positive")
        repo_id = self.repo_id or f"local/{Path(self.output_dir).name}"
        if repo_id.count("/") != 1 or not all(repo_id.split("/")):
            raise ConfigError(f"repo_id must look like ORG/NAME, got {repo_id!r}")
        members = self.ensemble_size or (5 if "doubt" in self.predictor else 1)
        return dataclasses.replace(
            self, repo_id=repo_id, ensemble_size=members, hidden=list(self.hidden), d_hidden=list(self.d_hidden)
        )


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
    predictor: str = "gda"
    """Rule whose requests `intervention_request` marks and the predictor file uses: beta or gda."""
    seed: int = 0
    """Seed of D's initialisation and batches."""
    d_steps: int | None = None
    """D's gradient steps (default: one per recorded frame)."""
    d_hidden: list[int] = field(default_factory=lambda: [256, 256])
    """Discriminator tanh MLP widths."""
    d_lr: float = 1e-3
    """Discriminator learning rate."""
    grad_penalty: float = 10.0
    """Discriminator gradient-penalty weight."""
    beta: int = 20
    """Initial beta of the beta rule."""
    gamma: float = 0.5
    """Initial posterior threshold of the GDA rule."""
    fp_cooldown: int = 5
    """Steps without requests after a refused one."""
    device: str = "auto"
    """auto, cpu or cuda."""
    progress: bool = False
    """Show a progress bar over D's training."""

    def check(self) -> None:
        """ConfigError (one line) for a bad value."""
        if self.predictor not in RULES:
            raise ConfigError(f"predictor must be one of {', '.join(RULES)}, got {self.predictor!r}")
        from shiftkit.datasets.hub import validate_repo_id

        validate_repo_id(self.repo_id)
        if self.d_steps is not None and self.d_steps <= 0:
            raise ConfigError(f"d_steps must be positive, got {self.d_steps}")
        if not self.d_lr > 0 or self.grad_penalty < 0 or self.beta <= 0 or self.fp_cooldown < 0:
            raise ConfigError("d_lr and beta must be positive, grad_penalty and fp_cooldown >= 0")
        if not 0.0 < self.gamma < 1.0:
            raise ConfigError(f"gamma must be in (0, 1), got {self.gamma}")
        if any(h <= 0 for h in self.d_hidden):
            raise ConfigError("d_hidden widths must be positive")
