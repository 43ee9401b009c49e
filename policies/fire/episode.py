"""One FIRE episode (thesis Algorithm 2, lines 3-34): the BC policy and D act (`Agent`), the failure
predictor watches, the simulated expert answers, takes over and hands back (`oracle.SimulatedOracle`),
and the episode comes back as dataset frames, its executed segments and the signals of the policy's
uninterrupted trajectory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.bc_policy import BCPolicy, ensemble_doubt
from shiftkit.policies.evaluation import ObservationMap
from shiftkit.policies.fire.aggregate import SOURCE_EXPERT, SOURCE_POLICY
from shiftkit.policies.fire.dagger_recording import runs
from shiftkit.policies.fire.discriminator import Discriminator
from shiftkit.policies.fire.failure_predictors import EpisodeTrace, Segment
from shiftkit.policies.fire.oracle import SimulatedOracle


class Agent:
    """The BC policy and D at one step: action (the members' mean), doubt (0 for one member) and D(s, a)."""

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
    """Signals of the policy's uninterrupted trajectory from the reset (executed part up to the first
    intervention + the oracle's look-ahead from there): what the ROC scores and labels use."""
    policy_failed: bool
    """Whether that uninterrupted trajectory fails (the label of the ROC curves and success curves)."""
    segments: list[Segment]
    """The executed stretches in order (policy / expert; a policy stretch that ends in an intervention
    failed), without D values: what GDA's statistics learn from."""
    interventions: list[dict[str, Any]]
    """Each expert takeover: start and end step (end: where the policy took control back, or the
    episode's length) and why ("tp": an agreed prediction, "fn": an unpredicted failure stopped)."""
    stops: list[dict[str, Any]]
    """Each unpredicted failure the oracle stopped: step and reason ("stalled" or "deadline")."""
    feedback: list[str]
    predictions: int


def _segments(intervention: np.ndarray, success: bool) -> list[Segment]:
    """The stretches of one episode from its per-frame `intervention` flags: a policy stretch failed
    when an expert stretch follows it, or when it ends an unsuccessful episode."""
    parts = runs(intervention)
    out = []
    for k, (start, end, expert) in enumerate(parts):
        failed = not expert and (k + 1 < len(parts) or not success)
        out.append(Segment(start, failed, expert, payload=(start, end)))
    return out


def run_episode(
    env: Any,
    seed: int,
    agent: Agent,
    predictor: Any,
    oracle: SimulatedOracle,
    active: bool,
    features: dict[str, dict],
    fp_cooldown: int,
) -> EpisodeResult:
    """Thesis Algorithm 2, lines 3-34: one episode of policy, predictions, oracle and expert.

    Until D is ready (`active` False) the policy runs on its own: no prediction, no stop, no takeover.
    Afterwards a predicted failure asks the oracle; an agreed one (or a failure the oracle stops
    itself) hands control to the expert, who gives it back as soon as the policy can finish from the
    current state; the policy may be stopped again later in the episode."""
    obs, info = env.reset(seed=seed)
    predictor.reset()
    oracle.start_episode()
    rows: list[dict[str, Any]] = []
    executed: list[dict[str, Any]] = []  # the policy's own steps until the first intervention
    expert, verdict = None, None
    feedback: list[str] = []
    interventions: list[dict[str, Any]] = []
    stops: list[dict[str, Any]] = []
    predictions, cooldown, t, success = 0, 0, 0, False
    while not success:  # at least one step, even where the reset state already counts as solved
        feats = agent.observe(env, obs)
        request = False
        if expert is not None and t > interventions[-1]["start"] and oracle.can_finish(env, obs, t):
            expert, interventions[-1]["end"] = None, t  # lines 27-28: the policy can finish from here
            predictor.reset()
        if expert is None:
            action, doubt = agent.decide(feats)
            d = agent.d_score(feats, action)
            if not interventions:
                executed.append({"d": d, "doubt": doubt})
            if active:
                asked = predictor.predict(t, d, doubt)
                answer = None
                if cooldown > 0:
                    cooldown -= 1
                elif asked:
                    request, predictions = True, predictions + 1
                    answer = "tp" if oracle.will_fail(env, obs, t) else "fp"
                    cooldown = fp_cooldown if answer == "fp" else 0
                elif reason := oracle.stops_unpredicted(env, obs, t):
                    answer = "fn"
                    stops.append({"step": t, "reason": reason})
                if answer is not None:
                    feedback.append(answer)
                    predictor.feedback(answer)
                if answer in ("tp", "fn"):
                    verdict = verdict or oracle.look_ahead
                    interventions.append({"start": t, "end": None, "kind": answer})
                    expert = oracle.take_over(env, seed=seed * 1000 + t)
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
    for stretch in interventions:
        stretch["end"] = t if stretch["end"] is None else stretch["end"]

    # the policy's uninterrupted trajectory: its executed steps, then the look-ahead that decided
    if interventions:
        first = interventions[0]["start"]
        signals, policy_failed = executed[:first] + verdict.records[first - verdict.start :], True
    else:
        signals, policy_failed = executed, not success
    trace = EpisodeTrace(
        d=np.array([s["d"] if active else np.nan for s in signals]), doubt=np.array([s["doubt"] for s in signals])
    )
    frames = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    segments = _segments(frames["intervention"][:, 0], success)
    return EpisodeResult(frames, success, trace, policy_failed, segments, interventions, stops, feedback, predictions)
