"""The arguments of `shiftkit train bc` (`BCArgs`): a module of their own without torch, so that the
command's options are built without importing the trainer (`training.py`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from shiftkit.pipelines.errors import ConfigError, require_positive

if TYPE_CHECKING:
    from shiftkit.policies.bc_policy import Normalization

REGIMES = ("early-stop", "fixed")
OUTPUT_ACTIVATIONS = ("linear", "tanh")


@dataclass
class BCArgs:
    """Arguments of `shiftkit train bc` (defaults follow the thesis, 3.6.3 and 4.4.2, but for one
    network instead of its 5-member ensembles: `ensemble_size`)."""

    datasets: list[str]
    """Dataset IDs or local dataset folders; several are trained on as one (same features)."""
    output_dir: str
    """Run folder: config, checkpoints, metrics.jsonl, model card."""
    root: str | None = None
    """Local folder of the dataset (with one dataset), else resolved by ID."""
    regime: str = "early-stop"
    """`early-stop` (hold-out validation, patience) or `fixed` (fixed steps with weight decay)."""
    steps: int | None = None
    """Gradient steps per member: required length of the `fixed` regime (default 20000); an upper
    bound in `early-stop` (default: max_epochs epochs)."""
    max_epochs: int = 200
    """early-stop: most epochs per member."""
    patience: int = 30
    """early-stop: epochs without validation improvement before a member stops."""
    batch_size: int = 64
    """Frames per gradient step and member."""
    lr: float | None = None
    """Learning rate (default 1e-3 early-stop, 3e-4 fixed; fixed halves it halfway)."""
    weight_decay: float | None = None
    """Decoupled (AdamW) weight decay (default 0 early-stop, 0.1 fixed)."""
    val_fraction: float | None = None
    """Share of episodes held out for validation (default 0.2 early-stop, 0 fixed)."""
    ensemble_size: int = 1
    """Networks trained side by side (different shuffles and init; the policy outputs their mean):
    1 is plain BC; the thesis' ensembles have 5 (training time grows with the count)."""
    inputs: list[str] | None = None
    """Observation features to use (default: every `observation.*` feature of the dataset)."""
    encoder: str = "cnn"
    """Image encoder: `cnn` (small CNN, 64x48 images) or `resnet18` (ResNet-18 trunk)."""
    encoder_weights: str | None = None
    """Local ResNet-18 state-dict file for the encoder's first layer (`cnn`) or trunk (`resnet18`)."""
    num_keypoints: int = 32
    """Spatial soft-argmax keypoints per camera."""
    hidden: list[int] = field(default_factory=lambda: [512, 512])
    """Widths of the fully connected layers after the encoders."""
    output_activation: str = "linear"
    """`linear` or `tanh` (actions bounded to [-1, 1], as the policy of thesis 5.4.2)."""
    seed: int = 0
    """Seed of the episode split, the shuffles and the init."""
    checkpoint_every: int = 1000
    """Save a checkpoint every this many steps (and at the end)."""
    log_every: int = 100
    """Write mean training loss to metrics.jsonl every this many steps."""
    norm_std_floor: float = 0.01
    """Floor of each dimension's normalisation std, as a share of the dimension's RMS value
    (`sqrt(mean^2 + std^2)`); 0 turns the floor off (the absolute floor 1e-6 stays)."""
    norm_clip: float | None = 10.0
    """Normalised inputs are clipped to +-this many (floored) stds; None: no clipping."""
    device: str = "auto"
    """`auto` (CUDA when present), `cpu` or `cuda[:N]`."""
    threads: int | None = 1
    """CPU threads for torch (None: torch's choice, one per core). One by default: a BC network's
    small matrix products gain little from more, and on a busy machine threads waiting for a core
    slow every step down (a state MLP on the shared 2-core machine: 65 steps/s on one thread, 3 on
    two, 2026-12-03); more can pay for camera encoders on an idle machine."""
    resume: bool = False
    """Continue the run in output_dir from its last checkpoint."""

    def resolved(self) -> BCArgs:
        """A copy with regime-dependent defaults filled in; raises ConfigError on bad values."""
        if self.regime not in REGIMES:
            raise ConfigError(f"unknown regime {self.regime!r} (choose from {', '.join(REGIMES)})")
        fixed = self.regime == "fixed"
        out = dataclasses.replace(
            self,
            steps=self.steps if self.steps is not None else (20000 if fixed else None),
            lr=self.lr if self.lr is not None else (3e-4 if fixed else 1e-3),
            weight_decay=self.weight_decay if self.weight_decay is not None else (0.1 if fixed else 0.0),
            val_fraction=self.val_fraction if self.val_fraction is not None else (0.0 if fixed else 0.2),
            datasets=list(self.datasets),
            hidden=list(self.hidden),
        )
        require_positive(
            out,
            "batch_size",
            "ensemble_size",
            "max_epochs",
            "patience",
            "checkpoint_every",
            "log_every",
            "num_keypoints",
            "lr",
        )
        if out.output_activation not in OUTPUT_ACTIVATIONS:
            raise ConfigError(
                f"unknown output activation {out.output_activation!r} (choose from {', '.join(OUTPUT_ACTIVATIONS)})"
            )
        if out.root is not None and len(out.datasets) != 1:
            raise ConfigError("--root names one dataset's folder; with several datasets give their IDs or paths")
        if out.threads is not None and out.threads <= 0:
            raise ConfigError(f"threads must be positive, got {out.threads}")
        if out.steps is not None and out.steps <= 0:
            raise ConfigError(f"steps must be positive, got {out.steps}")
        if not 0.0 <= out.val_fraction < 1.0:
            raise ConfigError(f"val_fraction must be in [0, 1), got {out.val_fraction}")
        if out.regime == "early-stop" and out.val_fraction == 0:
            raise ConfigError("the early-stop regime needs val_fraction > 0")
        if out.weight_decay < 0 or any(h <= 0 for h in out.hidden):
            raise ConfigError("weight_decay must be >= 0 and hidden widths positive")
        out.normalization()  # checks the normalisation values
        return out

    def normalization(self) -> Normalization:
        """The input normalisation these arguments ask for."""
        from shiftkit.policies.bc_policy import Normalization

        return Normalization(std_floor=self.norm_std_floor, clip=self.norm_clip)
