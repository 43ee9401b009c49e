"""The output folder every trainer writes (BC, VPACE, LfGP): config, checkpoints, metrics, model card.

    OUTPUT_DIR/
      config.json        {"trainer": "bc"|"vpace"|..., "args": {...full dataclass...},
                          "datasets": [{"id":..., "root":..., "revision":..., "fingerprint":..., "fps":...}], "seed": ...,
                          "versions": {"shiftkit":..., "lerobot":..., "torch":...}, ...}
      checkpoints/step-00001000.safetensors   the trainer's state (models, optimizers, rng states, "step",
                                     ...): every tensor and array in safetensors, the rest as the JSON
                                     document in its header's metadata ("shiftkit.state")
      checkpoints/last.txt           name of the newest complete checkpoint
      checkpoints/best.safetensors   (RL trainers) the policy at its best periodic evaluation
      metrics.jsonl      one JSON object per line, always with "step" and "split" ("train"/"eval"/...)
      README.md          model card rendered by shiftkit.cards
      card.json          the training metrics the card shows (so evaluations can re-render it)
      eval/*.json        evaluation results (`shiftkit eval`), summarised in the card

Checkpoints and last.txt are written to a temporary file and renamed into place, so a run killed at
any moment leaves the previous checkpoint loadable. A checkpoint is data, not code: it is read without
unpickling anything (`datasets/data_tree.py` rebuilds the state from the JSON document and the
tensors), so one pulled from a hub cannot run code when `shiftkit eval` or `--resume` loads it.
Checkpoints of older shiftkit versions (`step-*.pt`, `best.pt`: torch pickles) are still read, through
torch's weights-only loader only, which refuses any file holding more than tensors and plain values. Resuming drops the metric lines a killed run
wrote after its last checkpoint, so the metrics file reads as if the run had never stopped.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shiftkit.datasets import data_tree, loaders, provenance
from shiftkit.datasets.dataset import Dataset
from shiftkit.datasets.errors import ConfigError, DatasetError, ShiftkitError

CONFIG = "config.json"
METRICS = "metrics.jsonl"
CARD = "README.md"
CARD_METRICS = "card.json"
EVAL = "eval"
CHECKPOINTS = "checkpoints"
LAST = "last.txt"
SUFFIX = ".safetensors"
LEGACY_SUFFIX = ".pt"  # torch pickles of older shiftkit versions, read weights-only
BEST = "best" + SUFFIX
STATE_KEY = "shiftkit.state"


def versions() -> dict[str, Any]:
    """Installed versions of the packages a run's results depend on, and shiftkit's commit."""
    return provenance.versions(("shiftkit", "lerobot", "torch"))


def torch_device(name: str) -> torch.device:
    """`auto` (cuda when available, else cpu) or a torch device name; an unknown or absent device is a
    one-line ConfigError rather than torch's error at the first tensor moved there."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ConfigError(f"unknown device {name!r} (e.g. cpu, cuda, cuda:1, auto)") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {name!r} asked for, but torch sees no CUDA GPU here")
    return device


def run_folder(path: str | Path) -> Path:
    """The run folder of a run folder or of one of its checkpoint files (`RUN/checkpoints/step-*.safetensors`)."""
    path = Path(path)
    return path if path.is_dir() else path.parent.parent


def checkpoint_name(policy_path: str | Path) -> str | None:
    """The checkpoint file a policy path names (e.g. `best.safetensors`), or None for a run folder. Read
    from the path alone, so a model card can still say it after the file has been pruned."""
    path = Path(policy_path)
    return path.name if path.suffix in (SUFFIX, LEGACY_SUFFIX) else None


def checkpoint_bytes(state: dict) -> bytes:
    """`state` as a safetensors file: its tensors and arrays as tensors, the rest as the JSON document
    in the header's metadata (`data_tree`)."""
    from safetensors.torch import save

    doc, arrays = data_tree.split(state, (torch.Tensor,))
    tensors, storages = {}, set()
    for name, value in arrays.items():
        tensor = value if isinstance(value, torch.Tensor) else torch.from_numpy(np.array(value))
        tensor = tensor.detach().cpu().contiguous()
        storage = tensor.untyped_storage().data_ptr()
        if storage in storages:  # safetensors stores each storage once: a view of another tensor is copied
            tensor = tensor.clone()
        storages.add(tensor.untyped_storage().data_ptr())
        tensors[name] = tensor
    # One metadata entry: safetensors writes its metadata map in hash order, which differs from process to
    # process, so a second key (such as transformers' "format") would make the same checkpoint other bytes.
    return save(tensors, metadata={STATE_KEY: data_tree.dumps(doc)})


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict:
    """A checkpoint's state dict, read as data (no unpickling: a checkpoint someone sent cannot run code);
    a truncated, foreign or tampered file is a one-line DatasetError."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"checkpoint not found: {path}")
    if path.suffix == LEGACY_SUFFIX:
        state = _load_legacy(path, device)
    else:
        state = _load_safetensors(path, device)
    if not isinstance(state, dict):
        raise DatasetError(f"{path} is not a shiftkit checkpoint")
    return state


def _load_safetensors(path: Path, device: str | torch.device) -> Any:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            metadata = f.metadata() or {}
            tensors = {name: f.get_tensor(name) for name in f.keys()}  # noqa: SIM118 - safe_open has no iterator
    except Exception as exc:  # safetensors raises its own error types for a file that is not one
        raise DatasetError(
            f"{path} is not a readable checkpoint (not a safetensors file: {type(exc).__name__})"
        ) from None
    if STATE_KEY not in metadata:
        raise DatasetError(f"{path} is not a shiftkit checkpoint (its metadata has no {STATE_KEY!r})")
    return data_tree.join(data_tree.loads(metadata[STATE_KEY], str(path)), tensors, str(path))


def _load_legacy(path: Path, device: str | torch.device) -> Any:
    """A `.pt` checkpoint of an older shiftkit, through torch's weights-only unpickler only."""
    import pickle
    import zipfile

    if not zipfile.is_zipfile(path):  # torch.save writes a zip archive; anything else is no checkpoint
        raise DatasetError(f"{path} is not a readable checkpoint (not a torch checkpoint archive)")
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as exc:
        refused = " ".join(str(exc).split("\n")[0].split())[:160]
        raise DatasetError(
            f"{path}: refused: this .pt file holds more than tensors and plain values, and shiftkit never "
            f"unpickles code from a checkpoint ({refused})"
        ) from None
    except Exception as exc:  # torch raises many types for a file that is not a checkpoint
        raise DatasetError(f"{path} is not a readable checkpoint ({type(exc).__name__})") from None


def check_checkpoint_files(folder: Path) -> None:
    """Every checkpoint file of a run folder (a pulled one) reads as data: one line naming the first
    that does not. Its config.json, when there is one, is a run config."""
    if (folder / CONFIG).is_file():
        loaders.load_run_config(folder / CONFIG)
    for path in sorted(folder.rglob("*")):
        if path.suffix in (SUFFIX, LEGACY_SUFFIX) and path.is_file():
            load_checkpoint(path)


def dataset_records(resolved: list[Dataset]) -> list[dict[str, str | int | None]]:
    """The `datasets` entry of config.json: what a run trained on, pinned by content fingerprint, with
    its fps (the rate `shiftkit eval` runs the policy's env at)."""
    return [
        {
            "id": r.repo_id,
            "root": str(r.root),
            "revision": r.revision,
            "fingerprint": r.fingerprint,
            "fps": r.info["fps"],
        }
        for r in resolved
    ]


def trained_datasets(path: str | Path) -> list[dict]:
    """The `datasets` records of config.json of the run at `path` (a run folder or one of its
    checkpoints): what it trained on; [] for a run that names none or a folder that is no run."""
    config = RunDir(run_folder(path), resume=True).read_config() or {}
    return list(config.get("datasets", []))


def _atomic_write(path: Path, write) -> None:
    """Write through a temporary file renamed into place; a failed write (a full disk) leaves no
    temporary file and is one line."""
    import errno

    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.errno == errno.ENOSPC:
            raise ShiftkitError(f"no space left on device writing {path}") from None
        raise
    os.replace(tmp, path)


def _dotted(args: dict, prefix: str = "") -> dict:
    """`args` with each nested table's entries under dotted keys (`bc.hidden`), so that a refused
    resume names the one setting that differs."""
    out = {}
    for key, value in args.items():
        if isinstance(value, dict) and value:
            out.update(_dotted(value, f"{prefix}{key}."))
        else:
            out[prefix + key] = value
    return out


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:  # numpy / torch scalars
        return value.item()
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


class RunDir:
    """A trainer's output folder (layout in the module docstring)."""

    def __init__(self, output_dir: Path | str, resume: bool) -> None:
        self.path = Path(output_dir)
        self.resume = resume
        has_run = (self.path / CONFIG).exists() or (self.path / CHECKPOINTS).exists()
        if has_run and not resume:
            raise ShiftkitError(f"output folder {self.path} already holds a run; pass --resume or choose another")
        if self.path.exists() and not self.path.is_dir():
            raise ShiftkitError(f"output path {self.path} is a file, not a folder")

    @property
    def checkpoint_dir(self) -> Path:
        """The run's checkpoints folder."""
        return self.path / CHECKPOINTS

    def read_config(self) -> dict | None:
        """The stored config.json, or None before `write_config`."""
        path = self.path / CONFIG
        return loaders.load_run_config(path) if path.exists() else None

    def write_config(
        self,
        config: dict,
        ignore_on_resume: tuple[str, ...] = ("resume",),
        stored_args: Callable[[dict], dict] | None = None,
    ) -> None:
        """Store the run's config; on resume it must match the stored one's `args` (apart from the
        keys in `ignore_on_resume`), since a checkpoint only continues the run that made it.
        `stored_args` reads the stored `args` the way the trainer spells them now (a config written
        by an earlier version)."""
        config = _jsonable(config)
        old = self.read_config()
        if old is not None and not self.resume:  # it appeared after __init__: another run started there
            raise ShiftkitError(f"output folder {self.path} now holds another run's config; choose another --output")
        if old is not None:
            old_args, new_args = old.get("args", {}), config.get("args", {})
            old_args = _dotted(stored_args(old_args) if stored_args else old_args)
            new_args = _dotted(new_args)
            for key in sorted(set(old_args) | set(new_args)):
                if key not in ignore_on_resume and old_args.get(key) != new_args.get(key):
                    raise ConfigError(
                        f"--resume with a different {key!r} ({old_args.get(key)!r} in {self.path / CONFIG}, "
                        f"now {new_args.get(key)!r})"
                    )
        text = json.dumps(config, indent=2, sort_keys=True) + "\n"
        # The folder appears with the config, after a trainer has checked its data and env: a run that
        # fails to start leaves nothing that would block the corrected command.
        self.checkpoint_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write(self.path / CONFIG, lambda f: f.write(text.encode()))

    def save_checkpoint(self, step: int, state: dict, keep: int = 2) -> Path:
        """Write `state` (with `step` added) as checkpoints/step-XXXXXXXX.safetensors, point last.txt at
        it and delete all but the newest `keep` checkpoints (older `.pt` ones among them)."""
        name = f"step-{step:08d}{SUFFIX}"
        path = self.checkpoint_dir / name
        data = checkpoint_bytes({**state, "step": step})
        _atomic_write(path, lambda f: f.write(data))
        _atomic_write(self.checkpoint_dir / LAST, lambda f: f.write(name.encode()))
        steps = [*self.checkpoint_dir.glob(f"step-*{SUFFIX}"), *self.checkpoint_dir.glob(f"step-*{LEGACY_SUFFIX}")]
        for old in sorted(steps, key=lambda p: p.name)[:-keep] if keep > 0 else []:
            if old.name != name:
                old.unlink()
        return path

    def save_best(self, step: int, state: dict) -> Path:
        """Write `state` (with `step` added) as checkpoints/best.safetensors, replacing the previous best."""
        path = self.checkpoint_dir / BEST
        data = checkpoint_bytes({**state, "step": step})
        _atomic_write(path, lambda f: f.write(data))
        (self.checkpoint_dir / ("best" + LEGACY_SUFFIX)).unlink(missing_ok=True)  # a resumed older run's
        return path

    def latest_checkpoint(self) -> Path | None:
        """Path of the newest complete checkpoint, or None."""
        last = self.checkpoint_dir / LAST
        if not last.exists():
            return None
        name = last.read_text(errors="replace").strip()
        if not re.fullmatch(rf"step-\d{{8}}({re.escape(SUFFIX)}|{re.escape(LEGACY_SUFFIX)})", name):
            raise DatasetError(f"{last} does not name a checkpoint of this folder ({name[:60]!r})")
        path = self.checkpoint_dir / name
        if not path.is_file():
            raise ShiftkitError(f"{last} names a missing checkpoint {path.name}")
        return path

    def load_latest(self) -> dict | None:
        """The newest checkpoint's state (None if there is none); drops metric lines logged after it."""
        path = self.latest_checkpoint()
        if path is None:
            return None
        state = load_checkpoint(path)
        step = state.get("step")
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise DatasetError(f"{path}: its 'step' must be a non-negative integer, got {step!r}")
        self._truncate_metrics(step)
        return state

    def _truncate_metrics(self, after_step: int) -> None:
        path = self.path / METRICS
        if not path.exists():
            return
        lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
        steps = [line["step"] for line in loaders.load_metrics(path)]
        kept = [ln for ln, step in zip(lines, steps, strict=True) if step <= after_step]
        if len(kept) != len(lines):
            text = "".join(ln + "\n" for ln in kept)
            _atomic_write(path, lambda f: f.write(text.encode()))

    def log(self, step: int, split: str, **metrics: Any) -> None:
        """Append one metrics line `{"step", "split", **metrics}` to metrics.jsonl."""
        line = json.dumps(_jsonable({"step": step, "split": split, **metrics}), sort_keys=True)
        with open(self.path / METRICS, "a") as f:
            f.write(line + "\n")

    def read_metrics(self) -> list[dict]:
        """All metric lines, in order."""
        path = self.path / METRICS
        return loaders.load_metrics(path) if path.exists() else []

    def write_model_card(self, metrics: dict) -> None:
        """Render README.md from config.json, the final training `metrics` and the evaluations in eval/."""
        text = json.dumps(_jsonable(metrics), indent=2, sort_keys=True) + "\n"
        _atomic_write(self.path / CARD_METRICS, lambda f: f.write(text.encode()))
        self.refresh_model_card()

    def refresh_model_card(self) -> None:
        """Re-render README.md (e.g. after an evaluation wrote eval/*.json)."""
        from shiftkit.cards import render_model_card
        from shiftkit.policies.trainers import TRAINERS

        config = self.read_config()
        if config is None:
            raise ShiftkitError(f"{self.path} has no {CONFIG} to describe in a model card")
        stored = self.path / CARD_METRICS
        metrics = loaders.load_json_object(stored, "the run's card metrics") if stored.exists() else {}
        envs = []
        for path in sorted((self.path / EVAL).glob("*.json")):
            ev = loaders.load_evaluation(path)
            checkpoint = checkpoint_name(ev.get("policy", ""))
            name = (
                f"{ev['env']}/{ev['task']} ({f'{checkpoint}, ' if checkpoint else ''}{ev['episodes']} episodes "
                f"from seed {ev['seed']})"
            )
            lo, hi = ev["ci95"]
            metrics[f"success {name}"] = f"{ev['success_rate']:.1%} (95% CI {lo:.1%}-{hi:.1%})"
            envs.append(f"{ev['env']} / {ev['task']}")
        registered = TRAINERS.get(config["trainer"]) if config["trainer"] in TRAINERS else None
        card = {
            "trainer": config["trainer"],
            "citation": registered.citation if registered is not None else None,
            "datasets": config.get("datasets", []),
            "args": config.get("args", {}),
            "metrics": metrics,
            "env": ", ".join(dict.fromkeys(envs)) or config.get("env"),
            "versions": config.get("versions", {}),
            "normalization": config.get("normalization"),
        }
        text = render_model_card(card)
        _atomic_write(self.path / CARD, lambda f: f.write(text.encode()))
