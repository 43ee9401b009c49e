"""A fitted FIRE failure predictor that a rollout on a robot calls at every policy step.

`fire aggregate` (and the simulated `shiftkit fire`) write it as `meta/failure_predictor.pt` of the
aggregated dataset: the discriminator D(s, a), its input normalisation, and the beta and GDA rules
fitted on the recorded interventions (thesis 5.3-5.4). Two ways to use it:

* `FailurePredictor.load(path)`, then per policy step `score, request = predictor.predict(observation,
  action)`; `reset()` at an episode's start, `resume(steps)` when the policy takes control back
  after the operator drove `steps` frames (the rules' statistics are per episode step) and, once the
  operator answered a request, `feedback("tp" | "fp" | "fn")` so the rule adapts as it does inside FIRE;
* as a lerobot processor step, `shiftkit_failure_predictor` in lerobot's `ProcessorStepRegistry`
  (import this module first): it reads the transition's observation and action, puts
  `failure_score` and `intervention_request` into the transition's `info`, and tells the operator
  on the console (with a terminal bell) when it asks.

docs/fire.md shows the rollout loop and where the step goes.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.lerobot_types import TransitionKey
from lerobot.processor.pipeline import ProcessorStep, ProcessorStepRegistry

from shiftkit.datasets.errors import DatasetError
from shiftkit.policies.bc_policy import PolicySpec, is_image_feature
from shiftkit.policies.fire.config import RULES
from shiftkit.policies.fire.discriminator import Discriminator, DiscriminatorConfig
from shiftkit.policies.fire.failure_predictors import BetaRule, GDARule

FORMAT = "shiftkit-failure-predictor"
VERSION = 2  # 2: GDA keeps executed segments (smoothing, ROC-derived threshold)


def _plain(state: Any) -> Any:
    """Rule state with numpy arrays as lists (loadable with `torch.load(weights_only=True)`)."""
    if isinstance(state, dict):
        return {k: _plain(v) for k, v in state.items()}
    if isinstance(state, list | tuple):
        return [_plain(v) for v in state]
    if isinstance(state, np.ndarray):
        return state.tolist()
    if isinstance(state, np.generic):
        return state.item()
    return state


class FailurePredictor:
    """D(s, a) and one rule (`beta` or `gda`) deciding when to ask the operator."""

    def __init__(self, disc: Discriminator, spec: PolicySpec, rules: dict[str, Any], rule: str, fps: int) -> None:
        if rule not in RULES:
            raise ValueError(f"rule must be one of {RULES}, got {rule!r}")
        self.disc, self.spec, self.rules, self.rule_name, self.fps = disc, spec, rules, rule, int(fps)
        self.rule = rules[rule]
        self.t = 0

    # --- file
    def save(self, path: str | Path) -> None:
        """Write the predictor file atomically."""
        path = Path(path)
        state = {
            "format": FORMAT,
            "version": VERSION,
            "rule": self.rule_name,
            "fps": self.fps,
            "spec": _plain(dataclasses.asdict(self.spec)),
            "d_config": dataclasses.asdict(self.disc.config),
            "d_net": {k: v.detach().cpu() for k, v in self.disc.net.state_dict().items()},
            "rules": {name: _plain(r.state_dict()) for name, r in self.rules.items()},
        }
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        try:
            torch.save(state, tmp)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)

    @classmethod
    def load(cls, path: str | Path, rule: str | None = None, device: str = "cpu") -> FailurePredictor:
        """A predictor file; `rule` overrides the one it was written with. DatasetError (one line) for a
        file that is not one."""
        path = Path(path).expanduser()
        if not path.is_file():
            raise DatasetError(f"failure predictor file not found: {path}")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # torch raises many types for a damaged file
            raise DatasetError(f"{path} is not a readable failure predictor file ({type(exc).__name__})") from None
        if not isinstance(state, dict) or state.get("format") != FORMAT:
            raise DatasetError(f"{path} is not a shiftkit failure predictor file")
        if state.get("version") != VERSION:
            raise DatasetError(
                f"{path}: failure predictor version {state.get('version')!r}, this shiftkit reads {VERSION}"
            )
        spec = PolicySpec(**state["spec"])
        disc = Discriminator(spec, DiscriminatorConfig(**state["d_config"]), device)
        disc.net.load_state_dict(state["d_net"])
        disc.net.eval()
        beta, gda = BetaRule(), GDARule()
        beta.load_state_dict(state["rules"]["beta"])
        gda.load_state_dict(state["rules"]["gda"])
        return cls(disc, spec, {"beta": beta, "gda": gda}, rule or state["rule"], state["fps"])

    # --- use in a rollout
    def reset(self) -> None:
        """A new episode: the step count and the rule's watch restart."""
        self.t = 0
        self.rule.reset()

    def resume(self, steps: int) -> None:
        """The policy drives again after the operator's correction of `steps` frames: the episode's
        step count goes on, the rule's watch restarts."""
        self.t += int(steps)
        self.rule.reset()

    def _frame(self, observation: Mapping[str, Any], action: Any) -> dict[str, np.ndarray]:
        """One batch-of-one frame in the dataset's layout from robot-side values (numpy or torch,
        with or without a batch axis; cameras HWC or CHW, uint8 or float in [0, 1])."""
        frame = {}
        for key, ft in {**self.spec.features, "action": self.spec.action}.items():
            source = action if key == "action" else observation.get(key)
            if source is None:
                raise KeyError(f"the observation has no {key!r} (the predictor reads {', '.join(self.spec.features)})")
            x = source.detach().cpu().numpy() if isinstance(source, torch.Tensor) else np.asarray(source)
            shape = tuple(ft["shape"])
            if x.ndim == len(shape) + 1 and x.shape[0] == 1:
                x = x[0]
            if is_image_feature(ft) and x.shape != shape and x.shape == (shape[2], shape[0], shape[1]):
                x = np.moveaxis(x, 0, -1)
            if x.shape != shape:
                raise ValueError(f"{key}: shape {x.shape}, the predictor expects {shape}")
            if ft["dtype"] in ("image", "video") and x.dtype != np.uint8:
                x = np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)
            frame[key] = x[None] if ft["dtype"] in ("image", "video") else x[None].astype(np.float32)
        return frame

    def predict(self, observation: Mapping[str, Any], action: Any) -> tuple[float, bool]:
        """(D(s, a), whether to ask the operator now) for the policy's action at this step."""
        score = float(self.disc.score(self._frame(observation, action))[0])
        request = bool(self.rule.predict(self.t, score))
        self.t += 1
        return score, request

    def feedback(self, kind: str) -> None:
        """The operator's answer to a request ("tp": it would have failed, "fp": it would not) or an
        unpredicted failure the operator stopped ("fn")."""
        self.rule.feedback(kind)


@ProcessorStepRegistry.register("shiftkit_failure_predictor")
@dataclass
class FailurePredictorStep(ProcessorStep):
    """lerobot processor step around a `FailurePredictor`: adds `failure_score` and
    `intervention_request` to the transition's info and alerts the operator on a request."""

    path: str = ""
    """The predictor file (`meta/failure_predictor.pt` of an aggregated dataset)."""
    rule: str | None = None
    """`beta` or `gda` (default: the file's)."""
    device: str = "cpu"
    """Where D runs."""
    bell: bool = True
    """Ring the terminal bell with the console line on a request."""

    def __post_init__(self) -> None:
        self.predictor = FailurePredictor.load(self.path, self.rule, self.device)

    def __call__(self, transition: dict) -> dict:
        """The transition with `failure_score` and `intervention_request` in its info."""
        out = dict(transition)
        observation, action = out.get(TransitionKey.OBSERVATION), out.get(TransitionKey.ACTION)
        if observation is None or action is None:
            return out
        score, request = self.predictor.predict(observation, action)
        out[TransitionKey.INFO] = {
            **(out.get(TransitionKey.INFO) or {}),
            "failure_score": score,
            "intervention_request": request,
        }
        if request:
            print(
                f"{'\a' if self.bell else ''}shiftkit: failure predicted (D = {score:.3f}, "
                f"step {self.predictor.t - 1}): take over?",
                file=sys.stderr,
                flush=True,
            )
        return out

    def reset(self) -> None:
        """Starts a new episode: the rule's per-episode state is cleared."""
        self.predictor.reset()

    def get_config(self) -> dict[str, Any]:
        """What `from_pretrained` rebuilds the step from."""
        return {"path": self.path, "rule": self.rule, "device": self.device, "bell": self.bell}

    def transform_features(self, features: dict) -> dict:
        """Adds nothing to the observation or action (its results go to `info`)."""
        return features
