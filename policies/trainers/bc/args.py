"""The arguments of `shiftkit train bc` (`BCArgs`: BC's settings, `BCSettings`, and the run's inputs and
outputs): a module of their own without torch, so that the command's options are built without
importing the trainer (`training.py`). The commands that train a BC policy themselves nest
`BCSettings` (`FireArgs.bc`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from shiftkit.datasets.dataclass_config import check_fields, option
from shiftkit.datasets.errors import ConfigError

REGIMES = ("early-stop", "fixed")
FLAGS = {"ensemble_size": "ensemble", "num_keypoints": "keypoints"}
"""Field -> option name where it is not the field's (`--ensemble`; nested: `--bc.ensemble`)."""
OUTPUT_ACTIVATIONS = ("linear", "tanh")
EARLY_STOP_VAL_FRACTION = 0.2
"""The validation share of the early-stop regime when `val_fraction` is not given."""


@dataclass
class BCSettings:
    """BC's policy and training settings: what `shiftkit train bc` and the commands that train a BC
    policy themselves (`shiftkit fire`'s initial policy, `FireArgs.bc`) share."""

    regime: str = option("early-stop", choices=REGIMES)
    """`early-stop` (hold-out validation, patience) or `fixed` (fixed steps with weight decay)."""
    steps: int | None = option(None, rule="positive_int")
    """Gradient steps per member: required length of the `fixed` regime (default 20000); an upper
    bound in `early-stop` (default: max_epochs epochs)."""
    max_epochs: int = option(200, rule="positive_int")
    """early-stop: most epochs per member."""
    patience: int = option(30, rule="positive_int")
    """early-stop: epochs without validation improvement before a member stops."""
    batch_size: int = option(64, rule="positive_int")
    """Frames per gradient step and member."""
    lr: float | None = option(None, rule="positive_float")
    """Learning rate (default 1e-3 early-stop, 3e-4 fixed; fixed halves it halfway)."""
    weight_decay: float | None = option(None, rule="non_negative_float")
    """Decoupled (AdamW) weight decay (default 0 early-stop, 0.1 fixed)."""
    val_fraction: float | None = option(None, rule="fraction")
    """Share of episodes held out for validation (default 0.2 early-stop, 0 fixed)."""
    ensemble_size: int = option(1, rule="positive_int")
    """Networks trained side by side (different shuffles and init; the policy outputs their mean):
    1 is plain BC; the thesis' ensembles have 5 (training time grows with the count)."""
    inputs: list[str] | None = None
    """Observation features to use (default: every `observation.*` feature of the dataset)."""
    encoder: str = option("cnn", choices=("cnn", "resnet18"))
    """Image encoder: `cnn` (small CNN, 64x48 images) or `resnet18` (ResNet-18 trunk)."""
    encoder_weights: str | None = None
    """Local ResNet-18 state-dict file for the encoder's first layer (`cnn`) or trunk (`resnet18`)."""
    num_keypoints: int = option(32, rule="positive_int")
    """Spatial soft-argmax keypoints per camera."""
    hidden: list[int] = option(default_factory=lambda: [512, 512], rule="positive_int")
    """Widths of the fully connected layers after the encoders."""
    output_activation: str = option("linear", choices=OUTPUT_ACTIVATIONS)
    """`linear` or `tanh` (actions bounded to [-1, 1], as the policy of thesis 5.4.2)."""
    norm_std_floor: float = option(0.01, rule="fraction")
    """Floor of each dimension's normalisation std, as a share of the dimension's RMS value
    (`sqrt(mean^2 + std^2)`); 0 turns the floor off (the absolute floor 1e-6 stays)."""
    norm_clip: float | None = option(10.0, rule="positive_float")
    """Normalised inputs are clipped to +-this many (floored) stds; None: no clipping."""


@dataclass(kw_only=True)
class BCArgs(BCSettings):
    """Arguments of `shiftkit train bc` (defaults follow the thesis, 3.6.3 and 4.4.2, but for one
    network instead of its 5-member ensembles: `ensemble_size`)."""

    datasets: list[str]
    """Dataset IDs or local dataset folders; several are trained on as one (same features)."""
    output_dir: str
    """Run folder: config, checkpoints, metrics.jsonl, model card."""
    root: str | None = None
    """Local folder of the dataset (with one dataset), else resolved by ID."""
    seed: int = option(0, rule="non_negative_int")
    """Seed of the episode split, the shuffles and the init."""
    checkpoint_every: int = option(1000, rule="positive_int")
    """Save a checkpoint every this many steps (and at the end)."""
    log_every: int = option(100, rule="positive_int")
    """Write mean training loss to metrics.jsonl every this many steps."""
    device: str = "auto"
    """`auto` (CUDA when present), `cpu` or `cuda[:N]`."""
    threads: int | None = option(1, rule="positive_int")
    """CPU threads for torch (None: torch's choice, one per core). One by default: a BC network's
    small matrix products gain little from more, and on a busy machine threads waiting for a core
    slow every step down (a state MLP on the shared 2-core machine: 65 steps/s on one thread, 3 on
    two, 2026-12-03); more can pay for camera encoders on an idle machine."""
    resume: bool = False
    """Continue the run in output_dir from its last checkpoint."""

    def resolved(self) -> BCArgs:
        """A copy with regime-dependent defaults filled in; raises ConfigError on bad values (each field's
        rule, then what relates fields)."""
        check_fields(self)
        fixed, held_out = self.regime == "fixed", EARLY_STOP_VAL_FRACTION
        out = dataclasses.replace(
            self,
            steps=self.steps if self.steps is not None else (20000 if fixed else None),
            lr=self.lr if self.lr is not None else (3e-4 if fixed else 1e-3),
            weight_decay=self.weight_decay if self.weight_decay is not None else (0.1 if fixed else 0.0),
            val_fraction=self.val_fraction if self.val_fraction is not None else (0.0 if fixed else held_out),
            datasets=list(self.datasets),
            hidden=list(self.hidden),
        )
        if out.root is not None and len(out.datasets) != 1:
            raise ConfigError("--root names one dataset's folder; with several datasets give their IDs or paths")
        if out.regime == "early-stop" and out.val_fraction == 0:
            raise ConfigError("the early-stop regime needs val_fraction > 0")
        return out
