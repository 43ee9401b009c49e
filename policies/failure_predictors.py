"""FIRE's failure predictors (thesis 5.3-5.4, docs/fire.md): when should a running policy be stopped
and the expert asked "will the agent fail?".

Every predictor sees, at each autonomous step t, the discriminator score `d_t = D(s_t, a_t)` (None
before D trains) and the BC ensemble's doubt `||diag Cov||_2` of its members' actions, and:

* `reset()` at an episode's start;
* `predict(t, d_t, doubt_t) -> bool` (True: predicted failure, stop and ask);
* `feedback(kind)` with the expert's answer at once: "tp" (agreed), "fp" (disagreed: the predictor
  becomes more permissive by `delta_fp`) or "fn" (the expert stopped an unpredicted failure: more
  conservative by `delta_fn`);
* `update(episode, failed)` after the episode, with the signals along the policy's uninterrupted
  trajectory (`EpisodeTrace`) and whether that trajectory fails;
* `score(episode)`: one number per episode for ROC curves; the predictor with threshold x fires
  somewhere in the episode exactly when `score > x` (beta: `score >= beta`), so sweeping x traces the
  thesis' ROC (Fig. 5.5: a failed episode with any prediction is a true positive, a successful one
  without any a true negative).

After answering a question the watch restarts (consecutive counters go back to 0), so one long dip
of D is one question, not one per step. A false negative only counts against a predictor that could
have predicted in that episode (`watching`: it had a defined signal at some step); before D trains, or
before GDA has statistics, a D-based rule is not blamed for failures it could not see.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

FEEDBACK = ("tp", "fp", "fn")
PREDICTORS = ("beta", "gda", "doubt", "gda+doubt")


@dataclass
class EpisodeTrace:
    """Signals along one episode's policy trajectory (executed part + the oracle's look-ahead)."""

    d: np.ndarray
    """D(s_t, a_t) per step (NaN where D was not trained yet)."""
    doubt: np.ndarray
    """Ensemble doubt per step."""


def _check_feedback(kind: str) -> None:
    if kind not in FEEDBACK:
        raise ValueError(f"feedback must be one of {FEEDBACK}, got {kind!r}")


class BetaRule:
    """Rule 1 (Eq. 5.2): failure once D < 0.5 for `beta` consecutive steps; `beta` grows by
    `delta_fp` on a false positive and shrinks by `delta_fn` (to at least 1) on a false negative."""

    name = "beta"

    def __init__(self, beta: int = 20, delta_fp: int = 1, delta_fn: int = 3, threshold: float = 0.5) -> None:
        self.beta, self.delta_fp, self.delta_fn, self.threshold = beta, delta_fp, delta_fn, threshold
        self.run = 0
        self.watching = False

    def reset(self) -> None:
        """Starts a new episode: the run of low-D steps restarts."""
        self.run = 0
        self.watching = False

    def predict(self, t: int, d_t: float | None, doubt_t: float = 0.0) -> bool:
        """Whether step `t` (discriminator output `d_t`, None before it is available) is a predicted failure."""
        self.watching = self.watching or d_t is not None
        self.run = self.run + 1 if d_t is not None and d_t < self.threshold else 0
        return self.run >= self.beta

    def feedback(self, kind: str) -> None:
        """Adapts beta to the person's verdict on the last prediction: "fp" (false positive) or "fn" (missed failure)."""
        _check_feedback(kind)
        if kind == "fn" and not self.watching:
            return
        if kind == "fp":
            self.beta += self.delta_fp
        elif kind == "fn":
            self.beta = max(1, self.beta - self.delta_fn)
        self.run = 0

    def update(self, episode: EpisodeTrace, failed: bool) -> None:
        """The beta rule keeps no statistics."""

    def score(self, episode: EpisodeTrace) -> float:
        """The longest run of D < 0.5: the largest beta that still fires in this episode."""
        best = run = 0
        for d in episode.d:
            run = run + 1 if np.isfinite(d) and d < self.threshold else 0
            best = max(best, run)
        return float(best)

    def state_dict(self) -> dict[str, Any]:
        """The adapted state, for a checkpoint."""
        return {"beta": self.beta}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores what `state_dict` returned."""
        self.beta = state["beta"]


def _normal_pdf(x: float, mean: float, std: float) -> float:
    return math.exp(-0.5 * ((x - mean) / std) ** 2) / (std * math.sqrt(2.0 * math.pi))


class GDARule:
    """Rule 2 (Eqs. 5.3-5.5): per-timestep Gaussians of D_t for failed and successful trajectories
    (the last `window` of each) and the failure prior N_f / N over all episodes give
    `p(fail | D_t) = p(D_t | fail) N_f / (p(D_t | fail) N_f + p(D_t | success) N_s)`; failure when it
    exceeds `gamma` (for `beta` consecutive steps when `beta` is set, which then adapts as in the
    beta rule). `gamma` rises by `delta_fp` after a false positive, falls by `delta_fn` after a false
    negative, within [0.01, 0.99]. No prediction at a timestep until both classes have `min_count`
    values there (and at least one episode of each outcome)."""

    name = "gda"

    def __init__(
        self,
        gamma: float = 0.5,
        delta_fp: float = 0.02,
        delta_fn: float = 0.06,
        window: int = 25,
        min_count: int = 2,
        min_std: float = 1e-3,
        beta: int | None = None,
    ) -> None:
        self.gamma, self.delta_fp, self.delta_fn = gamma, delta_fp, delta_fn
        self.window, self.min_count, self.min_std = window, min_count, min_std
        self.beta = BetaRule(beta) if beta is not None else None
        self.failed: deque[np.ndarray] = deque(maxlen=window)
        self.succeeded: deque[np.ndarray] = deque(maxlen=window)
        self.n_failed = self.n_total = 0
        self._stats: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.run = 0
        self.watching = False

    # --- statistics
    def _fit(self) -> None:
        for name, trajs in (("fail", self.failed), ("success", self.succeeded)):
            length = max((len(x) for x in trajs), default=0)
            values = np.full((len(trajs), length), np.nan)
            for i, x in enumerate(trajs):
                values[i, : len(x)] = x
            finite = np.isfinite(values)
            count = finite.sum(axis=0)
            filled = np.where(finite, values, 0.0)
            mean = filled.sum(axis=0) / np.maximum(count, 1)
            std = np.sqrt((np.where(finite, (values - mean) ** 2, 0.0)).sum(axis=0) / np.maximum(count, 1))
            self._stats[name] = (mean, np.maximum(std, self.min_std), count)

    def update(self, episode: EpisodeTrace, failed: bool) -> None:
        """Adds a finished episode's D trace to the failed or succeeded statistics and refits."""
        (self.failed if failed else self.succeeded).append(np.asarray(episode.d, dtype=np.float64))
        self.n_failed += int(failed)
        self.n_total += 1
        self._fit()

    def refit(self, failed: list[np.ndarray], succeeded: list[np.ndarray]) -> None:
        """Replace the stored D trajectories (e.g. re-scored by a retrained D) and refit."""
        self.failed = deque((np.asarray(x, dtype=np.float64) for x in failed), maxlen=self.window)
        self.succeeded = deque((np.asarray(x, dtype=np.float64) for x in succeeded), maxlen=self.window)
        self._fit()

    def posterior(self, t: int, d_t: float | None) -> float | None:
        """p(fail | D_t = d_t), or None where the statistics cannot say."""
        if d_t is None or not np.isfinite(d_t) or self.n_failed == 0 or self.n_failed == self.n_total:
            return None
        (mf, sf, cf), (ms, ss, cs) = self._stats["fail"], self._stats["success"]
        if t >= len(cf) or t >= len(cs) or cf[t] < self.min_count or cs[t] < self.min_count:
            return None
        prior_f = self.n_failed / self.n_total
        mf, sf, ms, ss = float(mf[t]), float(sf[t]), float(ms[t]), float(ss[t])
        pf = _normal_pdf(float(d_t), mf, sf) * prior_f
        ps = _normal_pdf(float(d_t), ms, ss) * (1.0 - prior_f)
        if pf + ps == 0.0:  # both densities underflow: far from both classes, pick the nearer mean
            return float(abs(d_t - mf) / sf < abs(d_t - ms) / ss)
        return pf / (pf + ps)

    # --- prediction
    def reset(self) -> None:
        """Starts a new episode (and the beta counter, when the rule has one)."""
        self.run = 0
        self.watching = False
        if self.beta is not None:
            self.beta.reset()

    def predict(self, t: int, d_t: float | None, doubt_t: float = 0.0) -> bool:
        """Whether step `t` is a predicted failure: posterior > gamma (for beta consecutive steps, with a beta counter)."""
        p = self.posterior(t, d_t)
        self.watching = self.watching or p is not None
        above = p is not None and p > self.gamma
        if self.beta is None:
            return above
        self.run = self.run + 1 if above else 0
        return self.run >= self.beta.beta

    def feedback(self, kind: str) -> None:
        """Adapts gamma (and beta) to the person's verdict: "fp" raises it, "fn" lowers it."""
        _check_feedback(kind)
        if kind == "fn" and not self.watching:
            return
        if kind == "fp":
            self.gamma = min(0.99, self.gamma + self.delta_fp)
        elif kind == "fn":
            self.gamma = max(0.01, self.gamma - self.delta_fn)
        if self.beta is not None:
            self.beta.watching = True  # GDA's own watch decided above
            self.beta.feedback(kind)
        self.run = 0

    def score(self, episode: EpisodeTrace) -> float:
        """The episode's highest posterior (0 where the statistics cannot say)."""
        ps = [self.posterior(t, float(d)) for t, d in enumerate(episode.d)]
        return max((p for p in ps if p is not None), default=0.0)

    def state_dict(self) -> dict[str, Any]:
        """Gamma, the per-episode statistics and beta, for a checkpoint."""
        return {
            "gamma": self.gamma,
            "failed": list(self.failed),
            "succeeded": list(self.succeeded),
            "n_failed": self.n_failed,
            "n_total": self.n_total,
            "beta": self.beta.state_dict() if self.beta is not None else None,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores what `state_dict` returned and refits the class statistics."""
        self.gamma, self.n_failed, self.n_total = state["gamma"], state["n_failed"], state["n_total"]
        if self.beta is not None:
            self.beta.load_state_dict(state["beta"])
        self.refit(state["failed"], state["succeeded"])


class DoubtRule:
    """Ensemble doubt (Menda et al. 2019; thesis 5.4.5): failure when `||diag Cov||_2` of the BC
    members' actions exceeds `threshold`; the threshold grows by the fraction `delta_fp` after a false
    positive and shrinks by `delta_fn` after a false negative."""

    name = "doubt"

    def __init__(self, threshold: float, delta_fp: float = 0.05, delta_fn: float = 0.15) -> None:
        self.threshold, self.delta_fp, self.delta_fn = threshold, delta_fp, delta_fn

    def reset(self) -> None:
        """Doubt looks at one step at a time."""

    def predict(self, t: int, d_t: float | None, doubt_t: float = 0.0) -> bool:
        """Whether step `t` is a predicted failure: the ensemble doubt `doubt_t` exceeds the threshold."""
        return bool(doubt_t > self.threshold)

    def feedback(self, kind: str) -> None:
        """Scales the threshold by the person's verdict: up after "fp", down after "fn"."""
        _check_feedback(kind)
        if kind == "fp":
            self.threshold *= 1.0 + self.delta_fp
        elif kind == "fn":
            self.threshold *= 1.0 - self.delta_fn

    def update(self, episode: EpisodeTrace, failed: bool) -> None:
        """Doubt keeps no statistics."""

    def score(self, episode: EpisodeTrace) -> float:
        """The episode's highest doubt (0 for an empty trace)."""
        return float(np.max(episode.doubt)) if len(episode.doubt) else 0.0

    def state_dict(self) -> dict[str, Any]:
        """The adapted threshold, for a checkpoint."""
        return {"threshold": self.threshold}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores what `state_dict` returned."""
        self.threshold = state["threshold"]


class OrRule:
    """The logical OR of two predictors at every step (thesis 5.4.5: GDA or doubt)."""

    def __init__(self, a: Any, b: Any) -> None:
        self.a, self.b = a, b
        self.name = f"{a.name}+{b.name}"

    def reset(self) -> None:
        """Resets both predictors."""
        self.a.reset()
        self.b.reset()

    def predict(self, t: int, d_t: float | None, doubt_t: float = 0.0) -> bool:
        """Whether either predictor fires at step `t` (both are stepped)."""
        fa = self.a.predict(t, d_t, doubt_t)  # both run: each keeps its own counters
        fb = self.b.predict(t, d_t, doubt_t)
        return fa or fb

    def feedback(self, kind: str) -> None:
        """Passes the verdict to both predictors."""
        self.a.feedback(kind)
        self.b.feedback(kind)

    def update(self, episode: EpisodeTrace, failed: bool) -> None:
        """Passes the finished episode to both predictors."""
        self.a.update(episode, failed)
        self.b.update(episode, failed)

    def state_dict(self) -> dict[str, Any]:
        """Both predictors' states, for a checkpoint."""
        return {"a": self.a.state_dict(), "b": self.b.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores what `state_dict` returned."""
        self.a.load_state_dict(state["a"])
        self.b.load_state_dict(state["b"])


def make_predictor(name: str, doubt_threshold: float, beta: int = 20, gamma: float = 0.5) -> Any:
    """A predictor by CLI name (`PREDICTORS`)."""
    if name == "beta":
        return BetaRule(beta)
    if name == "gda":
        return GDARule(gamma)
    if name == "doubt":
        return DoubtRule(doubt_threshold)
    if name == "gda+doubt":
        return OrRule(GDARule(gamma), DoubtRule(doubt_threshold))
    raise ValueError(f"unknown predictor {name!r} (choose from {', '.join(PREDICTORS)})")


def quantile_or(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Episode scores of the OR of two predictors for one ROC curve: each score is replaced by its
    empirical quantile among the episodes, and the OR fires when either quantile exceeds the swept
    threshold, i.e. on their maximum (one threshold for both, at matching false-alarm levels)."""

    def quantile(x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        return np.searchsorted(np.sort(x), x, side="right") / max(len(x), 1)

    return np.maximum(quantile(a), quantile(b))


def roc_curve(scores: np.ndarray, failed: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """ROC of "score > x predicts failure" over every threshold x: (false positive rates, true positive
    rates, area under the curve, ties counted half). Needs episodes of both outcomes."""
    scores, failed = np.asarray(scores, dtype=np.float64), np.asarray(failed, dtype=bool)
    if failed.all() or not failed.any():
        raise ValueError("a ROC curve needs failed and successful episodes")
    thresholds = np.r_[np.inf, np.unique(scores)[::-1], -np.inf]
    tpr = np.array([(scores[failed] >= x).mean() for x in thresholds])
    fpr = np.array([(scores[~failed] >= x).mean() for x in thresholds])
    pos, neg = scores[failed], scores[~failed]
    auc = ((pos[:, None] > neg[None]).sum() + 0.5 * (pos[:, None] == neg[None]).sum()) / (len(pos) * len(neg))
    return fpr, tpr, float(auc)
