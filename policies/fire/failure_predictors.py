"""FIRE's failure predictors (thesis 5.3-5.4, docs/fire.md): when should a running policy be stopped
and the expert asked "will the agent fail?".

Every predictor sees, at each autonomous step t, the discriminator score `d_t = D(s_t, a_t)` (None
before D trains) and the BC ensemble's doubt `||diag Cov||_2` of its members' actions, and:

* `reset()` at an episode's start and whenever the policy takes control back from the expert;
* `predict(t, d_t, doubt_t) -> bool` (True: predicted failure, stop and ask; `t` is the episode step);
* `feedback(kind)` with the expert's answer at once: "tp" (agreed), "fp" (disagreed: the predictor
  becomes more permissive) or "fn" (the expert stopped an unpredicted failure: more conservative);
* `score(episode)`: one number per episode for ROC curves; the predictor with threshold x fires
  somewhere in the episode exactly when `score >= x` (beta: `score >= beta`), so sweeping x traces
  the thesis' ROC (Fig. 5.5: a failed episode with any prediction is a true positive, a successful one
  without any a true negative).

GDA also learns from the executed segments of every episode (`GDARule.add_segment`, `add_outcome`,
`rescore` after D trains); the beta rule and doubt keep no statistics.

After answering a question the watch restarts (consecutive counters go back to 0), so one long dip
of D is one question, not one per step. A false negative only counts against a predictor that could
have predicted in that episode (`watching`: it had a defined signal at some step); before D trains, or
before GDA has statistics, a D-based rule is not blamed for failures it could not see.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
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


@dataclass(eq=False)
class Segment:
    """One executed stretch of an episode, as GDA's statistics keep it (thesis 5.3.3; the reference
    implementation's `append_traj`): a stretch the policy drove, or an expert correction."""

    start: int
    """Episode step of its first frame (the statistics are per episode step)."""
    failed: bool
    """A policy stretch that ended in an intervention, or in its episode's failure (expert stretches:
    False)."""
    expert: bool = False
    """An expert correction: success-class data, as in the reference; never a ROC trajectory."""
    d: np.ndarray | None = None
    """D(s, a) per frame; None until a trained D scores it."""
    payload: Any = None
    """The frames behind `d` (features + action), kept to re-score them after D trains."""


class GDARule:
    """Rule 2 (Eqs. 5.3-5.5) as the authors' statistical predictor runs it (manipulator-learning,
    `failure_prediction_statistical.py`, mode `gda`):

    * statistics from executed segments (`add_segment`): per episode step t, the last `window` D values
      of failed policy segments (ended in an intervention) and of successful ones (ran to the episode's
      success; expert corrections count as successful data too), each class a Gaussian N(D_t | mu, sigma);
    * the failure prior: the share of failures among the last `prior_window` outcomes (`add_outcome`),
      clipped to [0.05, 0.95];
    * `p(fail | D_t)` by Bayes, smoothed by the mean over the last `smoothing` steps (the window
      starts full of zeros at each segment's start); failure when the smoothed posterior reaches
      `gamma` (for `beta` consecutive steps when `beta` is set, which then adapts as the beta rule);
    * `gamma` is re-derived from the ROC of the stored policy segments whenever the statistics change:
      a segment's score is its highest smoothed posterior, and of the thresholds that catch more
      than `min_tpr` of the failed segments the one closest to (FPR 0, TPR 1) is taken; an expert's
      verdict moves it until the next refit, by `change` x the range of the scores: up after a false
      positive, down after a false negative (within [0, 1]).

    No prediction at a step until both classes hold `min_count` values there."""

    name = "gda"

    def __init__(
        self,
        gamma: float = 0.5,
        window: int = 25,
        prior_window: int = 25,
        smoothing: int = 5,
        min_tpr: float = 0.8,
        change: float = 0.05,
        min_count: int = 2,
        min_std: float = 1e-3,
        beta: int | None = None,
    ) -> None:
        self.gamma, self.window, self.prior_window, self.smoothing = gamma, window, prior_window, smoothing
        self.min_tpr, self.change, self.min_count, self.min_std = min_tpr, change, min_count, min_std
        self.delta = 0.0
        """How far one verdict moves gamma (set by the ROC fit)."""
        self.beta = BetaRule(beta) if beta is not None else None
        self.segments: list[Segment] = []
        self.outcomes: deque[bool] = deque(maxlen=prior_window)
        self._stats: dict[bool, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.recent: deque[float] = deque([0.0] * smoothing, maxlen=smoothing)
        self.run = 0
        self.watching = False

    # --- statistics
    def add_segment(self, segment: Segment) -> None:
        """A finished segment joins the statistics (oldest values beyond `window` per step drop out)."""
        self.segments.append(segment)
        self._fit()

    def add_outcome(self, failed: bool) -> None:
        """An outcome for the failure prior (the sim loop: whether the policy alone failed the episode)."""
        self.outcomes.append(bool(failed))

    def rescore(self, score: Callable[[Any], np.ndarray]) -> None:
        """D changed: every stored segment's D values again from its frames (`score(payload)`), then refit."""
        for segment in self.segments:
            if segment.payload is not None:
                segment.d = np.asarray(score(segment.payload), dtype=np.float64)
        self._fit()

    def _fit(self) -> None:
        # newest first, the last `window` values per step and class; a segment that adds none is dropped
        length = max((s.start + self._length(s) for s in self.segments), default=0)
        sums = {c: np.zeros((3, length)) for c in (True, False)}  # count, sum, sum of squares
        seen = {c: np.zeros(length, dtype=int) for c in (True, False)}
        kept = []
        for segment in reversed(self.segments):
            steps = segment.start + np.arange(self._length(segment))
            take = seen[segment.failed][steps] < self.window
            if not take.any():
                continue
            kept.append(segment)
            seen[segment.failed][steps[take]] += 1
            if segment.d is not None:
                values = segment.d[take]
                np.add.at(sums[segment.failed], (0, steps[take]), 1.0)
                np.add.at(sums[segment.failed], (1, steps[take]), values)
                np.add.at(sums[segment.failed], (2, steps[take]), values**2)
        self.segments = kept[::-1]
        for failed, (count, total, squares) in sums.items():
            mean = total / np.maximum(count, 1)
            std = np.sqrt(np.maximum(squares / np.maximum(count, 1) - mean**2, 0.0))
            self._stats[failed] = (mean, np.maximum(std, self.min_std), count)
        self._fit_threshold()

    @staticmethod
    def _length(segment: Segment) -> int:
        return len(segment.d) if segment.d is not None else len(next(iter(segment.payload.values())))

    def _fit_threshold(self) -> None:
        """gamma from the ROC of the stored policy segments (see the class docstring)."""
        policy = [s for s in self.segments if not s.expert and s.d is not None]
        labels = np.array([s.failed for s in policy], dtype=bool)
        if labels.all() or not labels.any():
            return
        scores = np.array([self.score_segment(s.start, s.d) for s in policy])
        if not np.isfinite(scores).all():
            return
        candidates = np.linspace(scores.min() - 0.01, scores.max() + 0.01, 2 * len(policy))
        caught = scores[None, :] >= candidates[:, None]
        tpr, fpr = caught[:, labels].mean(axis=1), caught[:, ~labels].mean(axis=1)
        ok = np.flatnonzero(tpr > self.min_tpr)
        best = ok[np.argmin(np.hypot(fpr[ok], 1.0 - tpr[ok]))]
        self.gamma = float(np.clip(candidates[best], 0.0, 1.0))
        self.delta = self.change * float(scores.max() - scores.min())

    def score_segment(self, start: int, d: np.ndarray) -> float:
        """The highest smoothed posterior along a stretch of D values starting at episode step `start`
        (-inf where the statistics say nothing)."""
        recent = deque([0.0] * self.smoothing, maxlen=self.smoothing)
        best = -np.inf
        for i, d_t in enumerate(d):
            p = self.posterior(start + i, float(d_t))
            if p is not None:
                recent.append(p)
                best = max(best, float(np.mean(recent)))
        return best

    def prior(self) -> float:
        """p(fail): the recent outcomes' failure share, clipped to [0.05, 0.95] (0.5 before any)."""
        if not self.outcomes:
            return 0.5
        return float(np.clip(np.mean(self.outcomes), 0.05, 0.95))

    def posterior(self, t: int, d_t: float | None) -> float | None:
        """p(fail | D_t = d_t), or None where the statistics cannot say."""
        if d_t is None or not np.isfinite(d_t) or not self._stats:
            return None
        (mf, sf, cf), (ms, ss, cs) = self._stats[True], self._stats[False]
        if t >= len(cf) or t >= len(cs) or cf[t] < self.min_count or cs[t] < self.min_count:
            return None
        prior_f = self.prior()
        mf, sf, ms, ss = float(mf[t]), float(sf[t]), float(ms[t]), float(ss[t])
        pf = _normal_pdf(float(d_t), mf, sf) * prior_f
        ps = _normal_pdf(float(d_t), ms, ss) * (1.0 - prior_f)
        if pf + ps == 0.0:  # both densities underflow: far from both classes, pick the nearer mean
            return float(abs(d_t - mf) / sf < abs(d_t - ms) / ss)
        return pf / (pf + ps)

    # --- prediction
    def reset(self) -> None:
        """Starts a new segment (episode start, or the policy back in control): the smoothing window
        refills with zeros, the beta counter restarts."""
        self.recent = deque([0.0] * self.smoothing, maxlen=self.smoothing)
        self.run = 0
        self.watching = False
        if self.beta is not None:
            self.beta.reset()

    def predict(self, t: int, d_t: float | None, doubt_t: float = 0.0) -> bool:
        """Whether step `t` is a predicted failure: the smoothed posterior reaches gamma (for beta
        consecutive steps, with a beta counter)."""
        p = self.posterior(t, d_t)
        self.watching = self.watching or p is not None
        if p is not None:
            self.recent.append(p)
        above = p is not None and float(np.mean(self.recent)) >= self.gamma
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
            self.gamma = min(1.0, self.gamma + self.delta)
        elif kind == "fn":
            self.gamma = max(0.0, self.gamma - self.delta)
        if self.beta is not None:
            self.beta.watching = True  # GDA's own watch decided above
            self.beta.feedback(kind)
        self.run = 0

    def score(self, episode: EpisodeTrace, start: int = 0) -> float:
        """The highest smoothed posterior of a trace starting at episode step `start` (0 where the
        statistics cannot say)."""
        return max(self.score_segment(start, episode.d), 0.0)

    def state_dict(self, payloads: bool = False) -> dict[str, Any]:
        """Gamma, its step, the stored segments (their frames with `payloads`), the outcomes and beta."""
        return {
            "gamma": self.gamma,
            "delta": self.delta,
            "segments": [
                {
                    "start": s.start,
                    "failed": s.failed,
                    "expert": s.expert,
                    "d": s.d,
                    **({"payload": s.payload} if payloads else {}),
                }
                for s in self.segments
            ],
            "outcomes": list(self.outcomes),
            "beta": self.beta.state_dict() if self.beta is not None else None,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores what `state_dict` returned and refits the class statistics (gamma as saved). A
        segment saved before D scored it and without its frames is left out: it says nothing."""
        if self.beta is not None:
            self.beta.load_state_dict(state["beta"])
        self.outcomes = deque((bool(x) for x in state["outcomes"]), maxlen=self.prior_window)
        self.segments = [
            Segment(
                int(s["start"]),
                bool(s["failed"]),
                bool(s["expert"]),
                None if s["d"] is None else np.asarray(s["d"], dtype=np.float64),
                s.get("payload"),
            )
            for s in state["segments"]
            if s["d"] is not None or s.get("payload") is not None
        ]
        self._fit()
        self.gamma, self.delta = float(state["gamma"]), float(state["delta"])


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
