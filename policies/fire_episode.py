"""One FIRE episode (thesis Algorithm 2, lines 3-34): the BC ensemble and D act (`Agent`), the failure
predictor watches, the simulated expert answers and takes over (`oracle.SimulatedOracle`), and the
episode comes back as dataset frames plus the signals of the policy's uninterrupted trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.bc_policy import BCPolicy, ensemble_doubt
from shiftkit.policies.discriminator import Discriminator
from shiftkit.policies.evaluation import ObservationMap
from shiftkit.policies.failure_predictors import EpisodeTrace
from shiftkit.policies.fire_aggregate import SOURCE_EXPERT, SOURCE_POLICY
from shiftkit.policies.oracle import SimulatedOracle


class Agent:
    """The BC ensemble and D at one step: action (members' mean), doubt and D(s, a)."""

    def __init__(self, policy: BCPolicy, disc: Discriminator, obs_map: ObservationMap, device: torch.device) -> None:
        self.policy, self.disc, self.obs_map, self.device = policy, disc, obs_map, device
        self.keys = list(policy.features)

    def observe(self, env: Any, obs: np.ndarray) -> dict[str, np.ndarray]:
        """The policy's input features of the env observation `obs`."""
        return self.obs_map(env, obs)

    @torch.no_grad()
    def decide(self, features: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
        """(mean action, doubt) of the ensemble for one observation."""
        batch = {k: torch.as_tensor(features[k])[None].to(self.device) for k in self.keys}
        outs = self.policy.member_outputs(batch)
        return outs.mean(dim=0)[0].cpu().numpy().astype(np.float32), float(ensemble_doubt(outs)[0])

    def d_score(self, features: dict[str, np.ndarray], action: np.ndarray) -> float:
        """D(s, a) of one frame's features and action, in [0, 1]."""
        frame = {k: features[k][None] for k in self.keys}
        return float(self.disc.score({**frame, "action": action[None]})[0])

    def __call__(self, env: Any, obs: np.ndarray) -> tuple[np.ndarray, dict[str, Any]]:
        """One policy step (the oracle's look-ahead uses this too)."""
        features = self.observe(env, obs)
        action, doubt = self.decide(features)
        frame = {**{k: features[k] for k in self.keys}, "action": action}
        return action, {"d": self.d_score(features, action), "doubt": doubt, "frame": frame}


def recordable_features(features: dict[str, dict], observation_names: list[str]) -> dict[str, dict]:
    """The dataset's observation features (what the env recorder fills); ConfigError for features an
    executed episode could not hold."""
    known = {"action", "next.success", "sim.qpos", "sim.qvel"}
    odd = [k for k in features if not k.startswith("observation.") and k not in known]
    if odd:
        raise ConfigError(f"dataset feature {odd[0]!r} cannot be recorded from the environment")
    observed = {k: ft for k, ft in features.items() if k.startswith("observation.")}
    ObservationMap(observed, observation_names)  # raises for observations the env lacks
    return observed


@dataclass
class EpisodeResult:
    """One executed FIRE episode."""

    frames: dict[str, np.ndarray]
    """Dataset frames (dataset features + FIRE_FEATURES, timestamps and task added later)."""
    success: bool
    trace: EpisodeTrace
    """Signals of the policy's uninterrupted trajectory (executed part + look-ahead)."""
    trajectory: dict[str, np.ndarray]
    """That trajectory's policy inputs and actions (for re-scoring by a retrained D)."""
    policy_failed: bool
    """Whether that uninterrupted trajectory fails (the label of the ROC curves)."""
    feedback: list[str]
    intervened_at: int | None
    predictions: int


def run_episode(
    env: Any,
    seed: int,
    agent: Agent,
    predictor: Any,
    oracle: SimulatedOracle,
    d_ready: bool,
    features: dict[str, dict],
    fp_cooldown: int,
) -> EpisodeResult:
    """Thesis Algorithm 2, lines 3-34: one episode of policy, predictions, oracle and expert."""
    obs, info = env.reset(seed=seed)
    predictor.reset()
    oracle.start_episode()
    rows: list[dict[str, Any]] = []
    executed: list[dict[str, Any]] = []  # records of the policy's own steps
    expert, feedback, intervened_at, predictions, cooldown, t = None, [], None, 0, 0, 0
    success = False
    while not success:  # at least one step, even where the reset state already counts as solved
        feats = agent.observe(env, obs)
        request = False
        if expert is None:
            action, doubt = agent.decide(feats)
            d = agent.d_score(feats, action)
            executed.append({"d": d, "doubt": doubt, "frame": {**{k: feats[k] for k in agent.keys}, "action": action}})
            if cooldown > 0:
                cooldown -= 1
            elif predictor.predict(t, d if d_ready else None, doubt):
                request, predictions = True, predictions + 1
                if oracle.will_fail(env, obs, t):
                    feedback.append("tp")
                else:
                    feedback.append("fp")
                    cooldown = fp_cooldown
                predictor.feedback(feedback[-1])
            if not request and oracle.stops_unpredicted(env, obs, t):
                feedback.append("fn")
                predictor.feedback("fn")
            if feedback and feedback[-1] in ("tp", "fn") and intervened_at is None:
                intervened_at, expert = t, oracle.take_over(env)
        if expert is not None:
            action = np.asarray(expert.act(feats), dtype=np.float32)
            d = agent.d_score(feats, action)
        row = {k: feats[k] for k in features}
        row.update(
            action=action,
            intervention=np.array([expert is not None]),
            source=np.array([SOURCE_EXPERT if expert is not None else SOURCE_POLICY], dtype=np.int64),
            discriminator_score=np.array([d], dtype=np.float32),
            intervention_request=np.array([request]),
        )
        if "qpos" in info:
            row.update({"sim.qpos": info["qpos"], "sim.qvel": info["qvel"]})
        obs, _, terminated, truncated, info = env.step(action)
        success = bool(info.get("is_success", False))
        row["next.success"] = np.array([success])
        rows.append(row)
        t += 1
        if terminated or truncated:
            break

    # the policy's uninterrupted trajectory: its executed steps, then the look-ahead that decided
    look = oracle.look_ahead
    if intervened_at is not None:
        signals, policy_failed = executed[:intervened_at] + look.records[intervened_at - look.start :], True
    else:
        signals, policy_failed = executed, not success
    trace = EpisodeTrace(
        d=np.array([s["d"] if d_ready else np.nan for s in signals]), doubt=np.array([s["doubt"] for s in signals])
    )
    frames = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    trajectory = {k: np.stack([s["frame"][k] for s in signals]) for k in signals[0]["frame"]}
    return EpisodeResult(frames, success, trace, trajectory, policy_failed, feedback, intervened_at, predictions)
