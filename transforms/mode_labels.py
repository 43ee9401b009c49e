"""`mode_label`: label the STS sensor mode (1 tactile / 0 visual) as an action dimension (thesis
§4.3.7, docs/force_matching.md) and keep the STS image of the active mode.

The mode comes from the operator's mode-switch presses recorded in the raw episode (each press
toggles the mode, starting visual; `shiftkit collect --expert kinesthetic` records one press as
`mode_switch_step`) or automatically from a tactile contact signal: the distance of
a feature's chosen dims from their no-contact baseline (the median of the first frames), with
hysteresis (tactile once it reaches `on_threshold`, visual again once it falls below
`off_threshold`). `lead_steps` shifts either kind of label earlier (or later): the
demonstrator's choice of switching before, at or after contact (thesis §4.3.7). `action` gains a
dim named `sts_mode` (or that dim is overwritten when the action already has one).

The label is an action: the mode chosen at frame t acts with that frame's step, so the frame is
observed in the mode chosen at t - 1 (visual at an episode's start), as the env shows it to a
policy. With both STS image features given, they are replaced by one image feature holding the
image of that observed mode, and the state's mode dim and the dims that read zero in visual mode
follow it too. A policy thus learns to switch from frames that still show the visual image.

The fixed sources "visual" and "tactile" make the datasets of the fixed-mode baselines (thesis Fig.
4.13; the door env's `sensor_mode="visual"` / `"tactile"`): every frame is in that mode, so the
image feature holds that mode's image throughout, `action` loses its `sts_mode` dim (the env in a
fixed mode takes none), and the state shows what the env shows in that mode: its mode dim set, and
in visual mode the dims that read zero there (the door's marker wrench estimate) zeroed.

Each output episode records when the label first switches to tactile (`sts_mode_switch_step`)
and, when the raw episode knows the true first contact, the difference in steps
(`sts_mode_switch_minus_contact`); `timing_report` turns those into the thesis' Fig. 4.15
histogram and a table.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, override

import numpy as np

from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import Features
from shiftkit.pipelines.stage import FrameStage, register_stage
from shiftkit.transforms import papers

MODE_DIM = "sts_mode"
SWITCH_STEP = "sts_mode_switch_step"
SWITCH_MINUS_CONTACT = "sts_mode_switch_minus_contact"
FIXED_SOURCES = ("visual", "tactile")


@dataclass
class ModeLabelConfig:
    """Parameters of `mode_label`."""

    source: Literal["contact", "operator", "visual", "tactile"] = "contact"
    """Where labels come from: "contact" (the tactile signal, with hysteresis) or "operator" (the
    mode-switch presses in the episode's `labels`); "visual" / "tactile": that mode on every frame,
    for a fixed-mode baseline (no `sts_mode` action dim: it is removed if present)."""
    signal: str = "observation.wrench"
    """Feature holding the tactile contact signal (the raw unscaled wrench F~)."""
    signal_dims: list[str] = field(default_factory=lambda: ["Fz"])
    """Names of the signal's dims whose distance from the baseline is the contact signal (Euclidean
    norm over them)."""
    baseline_frames: int = 3
    """Frames at the episode start (out of contact) whose median is the no-contact baseline; 0 = none."""
    on_threshold: float = 0.4
    """Signal level (in the signal's units) at which the label becomes tactile."""
    off_threshold: float = 0.2
    """Signal level below which a tactile label returns to visual (hysteresis: <= on_threshold)."""
    press_label: str = "mode_switch_step"
    """Episode metadata key (in `labels` or at the top level) holding the frame(s) of the operator's
    mode-switch presses."""
    lead_steps: int = 0
    """Frames by which the label leads the presses or contact signal: the label at frame t is the
    mode detected at frame t + lead_steps (the last frame's beyond the end). Positive switches
    before contact, so that policies see the approach's last visual frames labelled tactile (at 0,
    a switch at contact leaves one such frame per episode); negative switches after it."""
    first_contact_key: str = "first_contact_step"
    """Episode metadata key of the true first-contact step (for the timing report); absent = unknown."""
    visual_image: str | None = None
    """STS visual-mode image feature (e.g. "observation.images.sts_visual"); None = no images."""
    tactile_image: str | None = None
    """STS tactile-mode image feature (e.g. "observation.images.sts_tactile"); None = no images."""
    image: str = "observation.images.sts"
    """Name of the image feature that keeps the active mode's image (replaces the two above)."""
    state: str = "observation.state"
    """Feature with the env's state, made to show the mode each frame is observed in (if present)."""
    state_mode_dim: str = MODE_DIM
    """Dim of `state` holding the observed mode (1 tactile / 0 visual), set if the state has it."""
    visual_zero_dims: list[str] = field(default_factory=lambda: ["sts_fx", "sts_fy", "sts_fz", "sts_tau_z"])
    """Dims of `state` that read zero in visual mode (the door env's marker wrench estimate: the
    markers are dark): zeroed on the frames observed in visual mode, those the state has."""
    late_switch: float = 0.0
    """Share of the tactile-labelled frames shown as the sensor would show them had it stayed in
    visual mode: the visual image, and `state` with its mode dim 0 and `visual_zero_dims` zeroed,
    while the label stays tactile. A policy that has not switched by contact sees such frames, which
    no demonstration holds; these teach it to switch at once. Drawn per frame from the stage's seed;
    needs both STS images (a simulated replay renders both). shiftkit's addition, not the thesis'."""

    def __post_init__(self) -> None:
        if self.off_threshold > self.on_threshold:
            raise ValueError(f"off_threshold {self.off_threshold} must be <= on_threshold {self.on_threshold}")
        if self.baseline_frames < 0:
            raise ValueError("baseline_frames must be >= 0")
        if not self.signal_dims:
            raise ValueError("signal_dims must name at least one dim")
        if (self.visual_image is None) != (self.tactile_image is None):
            raise ValueError("give both visual_image and tactile_image, or neither")
        if not 0.0 <= self.late_switch <= 1.0:
            raise ValueError(f"late_switch must be in [0, 1], got {self.late_switch}")
        if self.late_switch and (self.visual_image is None or self.source in FIXED_SOURCES):
            raise ValueError("late_switch needs visual_image and tactile_image and a contact or operator source")


@register_stage
class ModeLabel(FrameStage):
    """Adds the `sts_mode` action dimension (1 tactile / 0 visual) and keeps the active mode's STS image."""

    name = "mode_label"
    version = 2
    citation = papers.FORCE_MATCHING
    example_params = {
        "signal": "observation.state",
        "signal_dims": ["gripper"],
        "on_threshold": 1.0,
        "off_threshold": 0.5,
    }
    Config = ModeLabelConfig

    @override
    def transform_features(self, features: Features) -> Features:
        c = self.config
        action = features.get("action")
        if action is None or len(action["shape"]) != 1:
            raise ConfigError("mode_label: needs a vector 'action' feature")
        out = dict(features)
        names = list(action.get("names") or [f"action_{i}" for i in range(action["shape"][0])])
        self._mode_index = names.index(MODE_DIM) if MODE_DIM in names else None
        if c.source in FIXED_SOURCES:
            if self._mode_index is not None:
                kept = [n for n in names if n != MODE_DIM]
                out["action"] = {**copy.deepcopy(action), "shape": (len(kept),), "names": kept}
        elif self._mode_index is None:
            out["action"] = {**copy.deepcopy(action), "shape": (len(names) + 1,), "names": [*names, MODE_DIM]}
        state = features.get(c.state)
        state_names = list(state.get("names") or []) if state is not None and len(state["shape"]) == 1 else []
        self._state_mode_index = state_names.index(c.state_mode_dim) if c.state_mode_dim in state_names else None
        self._state_zero_indices = [state_names.index(d) for d in c.visual_zero_dims if d in state_names]
        if c.source == "contact":
            sig = features.get(c.signal)
            if sig is None or len(sig["shape"]) != 1:
                raise ConfigError(f"mode_label: no vector signal feature {c.signal!r}")
            sig_names = list(sig.get("names") or [])
            missing = [d for d in c.signal_dims if d not in sig_names]
            if missing:
                raise ConfigError(f"mode_label: {c.signal!r} has no dim(s) {missing} (dims: {', '.join(sig_names)})")
            self._signal_index = [sig_names.index(d) for d in c.signal_dims]
        if c.visual_image is not None:
            for key in (c.visual_image, c.tactile_image):
                if key not in features or features[key]["dtype"] not in ("image", "video"):
                    raise ConfigError(f"mode_label: no image feature {key!r}")
            visual, tactile = features[c.visual_image], features[c.tactile_image]
            if tuple(visual["shape"]) != tuple(tactile["shape"]):
                raise ConfigError(f"mode_label: {c.visual_image!r} and {c.tactile_image!r} differ in shape")
            if c.image in features and c.image not in (c.visual_image, c.tactile_image):
                raise ConfigError(f"mode_label: feature {c.image!r} already exists")
            merged = copy.deepcopy(visual)
            out = {k: v for k, v in out.items() if k not in (c.visual_image, c.tactile_image)}
            out[c.image] = merged
        return out

    @override
    def carried_features(self, features: Features) -> dict[str, str]:
        c = self.config
        labelled = {"action", c.state, c.image, c.visual_image, c.tactile_image}
        return {k: v for k, v in super().carried_features(features).items() if k not in labelled}

    @override
    def process(self, episode: Episode, rng: np.random.Generator) -> Iterable[Episode]:
        c = self.config
        n = len(episode)
        where = f"mode_label: episode {episode.meta.get('source_episode_index', '?')}"
        if c.source in FIXED_SOURCES:
            mode = np.full(n, float(c.source == "tactile"), dtype=np.float32)
        elif c.source == "operator":
            meta = episode.meta
            mode = operator_modes((meta.get("labels") or {}).get(c.press_label, meta.get(c.press_label)), n, where)
        else:
            signal = np.asarray(episode.frames[c.signal], dtype=np.float64).reshape(n, -1)[:, self._signal_index]
            mode = contact_modes(signal, c.baseline_frames, c.on_threshold, c.off_threshold)
        if c.source not in FIXED_SOURCES and c.lead_steps:
            mode = mode[np.clip(np.arange(n) + c.lead_steps, 0, n - 1)]
        frames = dict(episode.frames)
        action = np.asarray(episode.frames["action"])
        if c.source in FIXED_SOURCES:
            shown = np.full(n, c.source == "tactile")  # the frames observed in tactile mode
            if self._mode_index is not None:
                frames["action"] = np.delete(action, self._mode_index, axis=1)
        else:
            if self._mode_index is None:
                frames["action"] = np.concatenate([action, mode[:, None].astype(action.dtype)], axis=1)
            else:
                frames["action"] = action.copy()
                frames["action"][:, self._mode_index] = mode
            # The mode chosen at frame t acts with that frame's step, so the observation at t shows
            # the mode chosen at t - 1 (episodes start visual), as the env shows it to a policy.
            shown = np.concatenate([[False], mode[:-1] > 0])
            if c.late_switch:
                late = shown & (rng.random(n) < c.late_switch)
                shown &= ~late
        if c.state in frames and (self._state_mode_index is not None or self._state_zero_indices):
            state = np.array(episode.frames[c.state])
            if self._state_mode_index is not None:
                state[:, self._state_mode_index] = shown
            state[np.ix_(~shown, self._state_zero_indices)] = 0.0
            frames[c.state] = state
        if c.visual_image is not None:
            tactile = shown[:, None, None, None]
            image = np.where(tactile, episode.frames[c.tactile_image], episode.frames[c.visual_image])
            del frames[c.visual_image], frames[c.tactile_image]
            frames[c.image] = image
        meta = dict(episode.meta)
        switches = np.flatnonzero(mode > 0)
        meta[SWITCH_STEP] = int(switches[0]) if len(switches) else None
        contact = None if c.source in FIXED_SOURCES else meta.get(c.first_contact_key)  # no label timing
        meta[SWITCH_MINUS_CONTACT] = (
            meta[SWITCH_STEP] - int(contact) if contact is not None and meta[SWITCH_STEP] is not None else None
        )
        meta["sts_mode_source"] = c.source
        if c.late_switch:
            meta["sts_late_switch_frames"] = int(late.sum())
        yield Episode(frames, meta)


def operator_modes(presses: Any, n: int, where: str) -> np.ndarray:
    """Per-frame mode from toggling presses: frames from a press on take the toggled mode."""
    if presses is None:
        raise DatasetError(f"{where}: no operator mode-switch presses in the episode's labels")
    if isinstance(presses, (int, float)):
        presses = [presses]
    try:
        steps = sorted(int(p) for p in presses)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: mode-switch presses must be frame numbers, got {presses!r}") from None
    mode = np.zeros(n, dtype=np.float32)
    for step in steps:
        if not 0 <= step < n:
            raise DatasetError(f"{where}: mode-switch press at frame {step} is outside the {n} frames")
        mode[step:] = 1.0 - mode[step]
    return mode


def contact_modes(signal: np.ndarray, baseline_frames: int, on: float, off: float) -> np.ndarray:
    """Per-frame mode from a (T, D) contact signal with hysteresis around its baseline."""
    base = np.median(signal[:baseline_frames], axis=0) if baseline_frames else np.zeros(signal.shape[1])
    level = np.linalg.norm(signal - base, axis=1)
    mode = np.zeros(len(level), dtype=np.float32)
    active = False
    for t, value in enumerate(level):
        active = value >= on if not active else value >= off
        mode[t] = float(active)
    return mode


def timing_report(metas: list[dict[str, Any]], png: str | Path | None = None) -> str:
    """A markdown table of label-minus-first-contact steps per task (thesis Fig. 4.15) and, with
    `png`, their histograms. Episodes without a known first contact or switch are counted apart."""
    by_task: dict[str, list[int]] = {}
    unknown: dict[str, int] = {}
    for meta in metas:
        task = str(meta.get("task", "?"))
        diff = meta.get(SWITCH_MINUS_CONTACT)
        if diff is None:
            unknown[task] = unknown.get(task, 0) + 1
        else:
            by_task.setdefault(task, []).append(int(diff))
    lines = [
        "| task | episodes | within +-1 step | mean | min | max | no switch / no contact |",
        "|---|---|---|---|---|---|---|",
    ]
    for task in sorted(set(by_task) | set(unknown)):
        d = np.asarray(by_task.get(task, []))
        if len(d):
            within = f"{np.mean(np.abs(d) <= 1):.0%}"
            stats = f"{d.mean():+.2f} | {d.min():+d} | {d.max():+d}"
        else:
            within, stats = "-", "- | - | -"
        lines.append(f"| {task} | {len(d)} | {within} | {stats} | {unknown.get(task, 0)} |")
    if png is not None and by_task:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        tasks = sorted(by_task)
        fig, axs = plt.subplots(1, len(tasks), figsize=(3.2 * len(tasks), 2.8), squeeze=False, constrained_layout=True)
        for ax, task in zip(axs[0], tasks, strict=True):
            d = np.asarray(by_task[task])
            lo, hi = min(d.min(), -3), max(d.max(), 3)
            ax.hist(d, bins=np.arange(lo - 0.5, hi + 1.5), color="tab:blue", edgecolor="k")
            ax.set_title(task, fontsize=9)
            ax.set_xlabel("mode switch - first contact (steps)")
        axs[0][0].set_ylabel("episodes")
        fig.savefig(png, dpi=90)
        plt.close(fig)
    return "\n".join(lines)


def dataset_timing_report(root: str | Path, png: str | Path | None = None) -> str:
    """`timing_report` over the episodes of a LeRobot dataset written with a `mode_label` stage."""
    import json

    from shiftkit.datasets.episode import META_COLUMN
    from shiftkit.datasets.reader import open_lerobot_dataset

    reader = open_lerobot_dataset(root)
    if META_COLUMN not in reader.episodes:
        raise DatasetError(f"{root}: no shiftkit episode metadata (not written by a shiftkit pipeline)")
    metas = [json.loads(m) if isinstance(m, str) else {} for m in reader.episodes[META_COLUMN]]
    if not any(SWITCH_STEP in m for m in metas):
        raise DatasetError(f"{root}: no episode has mode labels (run a mode_label stage)")
    return timing_report(metas, png)
