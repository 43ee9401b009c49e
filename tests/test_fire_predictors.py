"""FIRE failure predictors: beta update rules, GDA step by step as the authors' statistical predictor
runs it (statistics from executed segments, smoothing, ROC-derived threshold) against hand
computations, doubt, their OR, ROC curves, and the discriminator learning to tell expert from policy
frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shiftkit.policies.fire.failure_predictors import (
    BetaRule,
    DoubtRule,
    EpisodeTrace,
    GDARule,
    OrRule,
    Segment,
    make_predictor,
    quantile_or,
    roc_curve,
)


def trace(d, doubt=None) -> EpisodeTrace:
    d = np.asarray(d, dtype=float)
    return EpisodeTrace(d=d, doubt=np.zeros_like(d) if doubt is None else np.asarray(doubt, dtype=float))


def test_beta_fires_after_beta_consecutive_low_scores():
    rule = BetaRule(beta=3)
    assert [rule.predict(t, d) for t, d in enumerate([0.4, 0.4, 0.6, 0.4, 0.4])] == [False] * 5
    rule.reset()
    assert [rule.predict(t, d) for t, d in enumerate([0.4, 0.3, 0.2])] == [False, False, True]
    # no score yet (D untrained) breaks a run
    rule.reset()
    assert [rule.predict(t, d) for t, d in enumerate([0.4, None, 0.4, 0.4])] == [False] * 4


def test_beta_update_rules():
    rule = BetaRule()
    assert rule.beta == 20
    rule.feedback("fn")
    assert rule.beta == 20  # no D score seen this episode: it could not have predicted
    rule.predict(0, 0.9)
    rule.feedback("fp")
    assert rule.beta == 21  # false positive: +delta_fp (1)
    rule.feedback("fn")
    assert rule.beta == 18  # false negative: -delta_fn (3)
    rule.feedback("tp")
    assert rule.beta == 18  # agreed: unchanged
    small = BetaRule(beta=2)
    small.predict(0, 0.9)
    small.feedback("fn")
    assert small.beta == 1  # never below one step
    # answering restarts the watch: the run of low scores counts again from zero
    rule = BetaRule(beta=2)
    assert [rule.predict(t, 0.1) for t in range(2)] == [False, True]
    rule.feedback("fp")
    assert [rule.predict(t, 0.1) for t in range(3)] == [False, False, True]
    with pytest.raises(ValueError, match="feedback"):
        rule.feedback("maybe")
    assert BetaRule().score(trace([0.4, 0.4, 0.9, 0.1, 0.2, 0.3, np.nan, 0.2])) == 3


def seg(start, d, failed=False, expert=False) -> Segment:
    return Segment(start, failed, expert, d=np.asarray(d, dtype=float))


def _pdf(x, m, s):
    return math.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2 * math.pi))


def test_gda_posterior_from_executed_segments_matches_hand_computation():
    """Statistics per episode step from executed segments (thesis 5.3.3, the reference's
    `append_traj`): a failed policy segment that started at step 3 feeds steps 3.., an expert
    correction counts as successful data, the prior is the recent outcomes' failure share."""
    gda = GDARule(min_count=2)
    gda.add_segment(seg(3, [0.2, 0.1], failed=True))  # steps 3, 4
    gda.add_segment(seg(3, [0.4, 0.3], failed=True))
    gda.add_segment(seg(0, [0.9, 0.9, 0.9, 0.7]))  # a success, steps 0-3
    gda.add_segment(seg(3, [0.9], expert=True))  # an expert correction at step 3: success class
    for failed in (True, True, False):
        gda.add_outcome(failed)
    # step 3: fail values 0.2, 0.4 (mean 0.3, std 0.1); success values 0.7, 0.9 (mean 0.8, std 0.1)
    prior_f = 2 / 3
    pf, ps = _pdf(0.45, 0.3, 0.1) * prior_f, _pdf(0.45, 0.8, 0.1) * (1 - prior_f)
    assert gda.posterior(3, 0.45) == pytest.approx(pf / (pf + ps), rel=1e-9)
    # steps where a class has fewer than min_count values say nothing; so does a missing score
    assert gda.posterior(0, 0.5) is None and gda.posterior(4, 0.2) is None and gda.posterior(3, None) is None
    # the prior is clipped to [0.05, 0.95] and covers the last prior_window outcomes only
    for _ in range(30):
        gda.add_outcome(True)
    assert gda.prior() == 0.95


def test_gda_keeps_the_last_window_values_per_step():
    gda = GDARule(window=2, min_count=1)
    gda.add_segment(seg(0, [0.1, 0.1], failed=True))
    gda.add_segment(seg(1, [0.3], failed=True))
    gda.add_segment(seg(1, [0.5], failed=True))  # step 1 now holds 0.3, 0.5; step 0 still 0.1
    gda.add_segment(seg(0, [0.9, 0.9]))
    mean, _, count = gda._stats[True]
    np.testing.assert_allclose(mean[:2], [0.1, 0.4])
    np.testing.assert_array_equal(count[:2], [1, 2])
    first = gda.segments[0]
    gda.add_segment(seg(0, [0.7], failed=True))  # step 0: 0.7, 0.1
    assert gda._stats[True][0][0] == pytest.approx(0.4) and first in gda.segments
    gda.add_segment(seg(0, [0.5], failed=True))  # step 0: 0.5, 0.7: the first segment adds nothing now
    assert gda._stats[True][0][0] == pytest.approx(0.6) and first not in gda.segments


def test_gda_smooths_the_posterior_over_five_steps_and_fits_gamma_by_roc():
    """The reference's rule: the posterior's mean over the last 5 steps (zeros before the segment's
    first) reaches gamma; gamma is the ROC threshold (TPR > 0.8, closest to (0, 1)) over the stored
    policy segments' highest smoothed posteriors; a verdict moves it by 5% of their range."""
    gda = GDARule(min_count=1)
    rng = np.random.default_rng(0)
    for _ in range(6):
        gda.add_segment(seg(0, rng.uniform(0.0, 0.3, 8), failed=True))
        gda.add_segment(seg(0, rng.uniform(0.6, 1.0, 8)))
    gda.add_outcome(True)
    gda.add_outcome(False)
    policy = [s for s in gda.segments if not s.expert]
    scores = []
    for s in policy:  # by hand: smoothed posterior along each segment, its maximum
        window = [0.0] * 5
        best = 0.0
        for t, d in enumerate(s.d):
            window = [*window[1:], gda.posterior(t, d)]
            best = max(best, sum(window) / 5)
        scores.append(best)
    scores, failed = np.array(scores), np.array([s.failed for s in policy])
    candidates = np.linspace(scores.min() - 0.01, scores.max() + 0.01, 2 * len(policy))
    tpr = np.array([(scores[failed] >= c).mean() for c in candidates])
    fpr = np.array([(scores[~failed] >= c).mean() for c in candidates])
    ok = np.flatnonzero(tpr > 0.8)
    expected = candidates[ok[np.argmin(np.hypot(fpr[ok], 1 - tpr[ok]))]]
    assert gda.gamma == pytest.approx(expected)
    assert gda.delta == pytest.approx(0.05 * (scores.max() - scores.min()))
    # online: one low D value is smoothed (1/5 of it), a run of them reaches gamma
    gda.reset()
    low = float(policy[0].d[0]) if policy[0].failed else float(policy[1].d[0])
    p = gda.posterior(0, low)
    assert gda.predict(0, low) is (p / 5 >= gda.gamma)
    fired = [gda.predict(t, 0.05) for t in range(1, 8)]
    assert any(fired)
    gamma = gda.gamma
    gda.feedback("fp")
    assert gda.gamma == pytest.approx(min(1.0, gamma + gda.delta))
    gda.feedback("fn")
    assert gda.gamma == pytest.approx(min(1.0, gamma + gda.delta) - gda.delta)
    restored = GDARule()
    restored.load_state_dict(gda.state_dict())
    assert restored.gamma == gda.gamma and len(restored.segments) == len(gda.segments)
    assert restored.posterior(3, 0.2) == gda.posterior(3, 0.2)


def test_gda_needs_both_outcomes_and_is_blamed_only_when_watching():
    gda = GDARule(gamma=0.5, min_count=1)
    gda.add_segment(seg(0, [0.1, 0.1], failed=True))
    gda.add_outcome(True)
    assert gda.posterior(0, 0.1) is None and gda.predict(0, 0.1) is False  # no successful segment yet
    gda.delta = 0.1
    gda.feedback("fn")
    assert gda.gamma == 0.5  # without statistics it could not have predicted: not blamed
    # segments without D values (D not trained yet) hold their place; `rescore` fills them in
    gda.add_segment(Segment(0, False, payload={"x": np.array([0.9, 0.8])}))
    assert gda.posterior(0, 0.5) is None
    # a checkpoint taken now (before D) restores: with frames the segment is kept, without it is dropped
    with_frames, without = GDARule(min_count=1), GDARule(min_count=1)
    with_frames.load_state_dict(gda.state_dict(payloads=True))
    without.load_state_dict(gda.state_dict())
    assert len(with_frames.segments) == 2 and len(without.segments) == 1
    for rule in (gda, with_frames):
        rule.rescore(lambda frames: frames["x"])
    assert gda.posterior(0, 0.5) is not None
    assert with_frames.posterior(0, 0.5) == gda.posterior(0, 0.5)


def test_gda_with_beta_needs_consecutive_steps():
    gda = GDARule(beta=2, min_count=1, smoothing=1)
    for d, failed in ((0.1, True), (0.2, True), (0.9, False), (0.8, False)):
        gda.add_segment(seg(0, [d] * 4, failed))
        gda.add_outcome(failed)
    gda.gamma = 0.5
    assert [gda.predict(t, 0.15) for t in range(3)] == [False, True, True]
    gda.delta = 0.02
    gda.feedback("fp")
    assert gda.beta.beta == 3 and gda.gamma == pytest.approx(0.52)
    gda.feedback("fn")
    assert gda.beta.beta == 1 and gda.gamma == pytest.approx(0.50)


def test_doubt_and_or():
    doubt = DoubtRule(threshold=1.0)
    assert doubt.predict(0, None, 1.5) and not doubt.predict(0, None, 0.5)
    doubt.feedback("fp")
    assert doubt.threshold == pytest.approx(1.05)
    either = OrRule(BetaRule(beta=1), DoubtRule(threshold=1.0))
    assert either.name == "beta+doubt"
    assert either.predict(0, 0.9, 2.0) and either.predict(0, 0.1, 0.0) and not either.predict(0, 0.9, 0.0)
    assert make_predictor("gda+doubt", 0.5).name == "gda+doubt"
    with pytest.raises(ValueError, match="unknown predictor"):
        make_predictor("psychic", 0.5)


def test_roc_curve_and_quantile_or():
    fpr, tpr, auc = roc_curve(np.array([0.9, 0.8, 0.3, 0.1]), np.array([True, True, False, False]))
    assert auc == 1.0 and fpr[0] == 0 and tpr[-1] == 1 and fpr[-1] == 1
    assert roc_curve(np.array([0.5, 0.5]), np.array([True, False]))[2] == 0.5
    _, _, auc = roc_curve(np.array([0.1, 0.9, 0.5]), np.array([True, False, True]))
    assert auc == pytest.approx(0.0)
    with pytest.raises(ValueError):
        roc_curve(np.array([0.1]), np.array([True]))
    np.testing.assert_allclose(quantile_or(np.array([3.0, 1.0, 2.0]), np.array([0.0, 5.0, 1.0])), [1.0, 1.0, 2 / 3])


def _spec():
    from shiftkit.policies.bc_policy import PolicySpec

    return PolicySpec(
        features={"observation.state": {"dtype": "float32", "shape": [3], "names": ["a", "b", "c"]}},
        action={"dtype": "float32", "shape": [2], "names": ["x", "y"]},
        stats={"observation.state": {"mean": [0.0] * 3, "std": [1.0] * 3}, "action": {"mean": [0, 0], "std": [1, 1]}},
        encoder="cnn",
        num_keypoints=4,
        hidden=[16],
        ensemble_size=2,
    )


def test_discriminator_tells_expert_from_policy_and_waits_for_samples():
    from shiftkit.policies.fire.discriminator import Discriminator, DiscriminatorConfig
    from shiftkit.policies.frame_buffer import FrameBuffer

    rng = np.random.default_rng(0)
    keys = ["observation.state", "action"]
    expert, policy = FrameBuffer(keys), FrameBuffer(keys)
    states = rng.normal(size=(400, 3)).astype(np.float32)
    # same states; the expert's action is a function of the state, the policy's is off by 1.5
    expert.add({"observation.state": states[:200], "action": states[:200, :2]})
    policy.add({"observation.state": states[200:], "action": states[200:, :2] + 1.5})
    disc = Discriminator(_spec(), DiscriminatorConfig(hidden=[32, 32], start_after=300), seed=0)
    assert not disc.ready(len(policy)) and disc.ready(300)
    metrics = disc.update(expert, policy, steps=150, rng=rng)
    assert metrics["d_accuracy"] > 0.8 and disc.updates == 150
    test = rng.normal(size=(100, 3)).astype(np.float32)
    on = disc.score({"observation.state": test, "action": test[:, :2]})
    off = disc.score({"observation.state": test, "action": test[:, :2] + 1.5})
    assert on.shape == (100,) and on.min() >= 0 and on.max() <= 1
    assert on.mean() > 0.6 and off.mean() < 0.4 and (on > off).mean() > 0.95
    clone = Discriminator(_spec(), DiscriminatorConfig(hidden=[32, 32]), seed=5)
    clone.load_state_dict(disc.state_dict())
    np.testing.assert_array_equal(clone.score({"observation.state": test, "action": test[:, :2]}), on)
