"""FIRE failure predictors: beta update rules, the GDA posterior against a hand computation, doubt,
their OR, ROC curves, and the discriminator learning to tell expert from policy frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shiftkit.policies.failure_predictors import (
    BetaRule,
    DoubtRule,
    EpisodeTrace,
    GDARule,
    OrRule,
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


def test_gda_posterior_matches_hand_computation():
    gda = GDARule(gamma=0.5)
    # failed episodes: D at t=1 is 0.2 and 0.4 -> mean 0.3, std 0.1 (population std)
    gda.update(trace([0.5, 0.2]), failed=True)
    gda.update(trace([0.5, 0.4]), failed=True)
    # successful episodes: D at t=1 is 0.7 and 0.9 -> mean 0.8, std 0.1; 3 of them (0.8 twice)
    for d in (0.7, 0.9, 0.8):
        gda.update(trace([0.5, d]), failed=False)
    # success at t=1: values 0.7, 0.9, 0.8 -> mean 0.8, std sqrt(2/300)
    s_std = math.sqrt(((0.7 - 0.8) ** 2 + (0.9 - 0.8) ** 2 + 0.0) / 3)
    d = 0.45
    pdf = lambda x, m, s: math.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2 * math.pi))  # noqa: E731
    prior_f = 2 / 5
    pf = pdf(d, 0.3, 0.1) * prior_f
    ps = pdf(d, 0.8, s_std) * (1 - prior_f)
    assert gda.posterior(1, d) == pytest.approx(pf / (pf + ps), rel=1e-9)
    assert gda.predict(1, d) is True  # posterior ~1 > gamma 0.5
    assert gda.predict(1, 0.85) is False
    # t=0: identical values in both classes -> std floor, equal likelihoods, posterior = prior
    assert gda.posterior(0, 0.5) == pytest.approx(prior_f)
    # beyond the recorded length, or without a score: no prediction
    assert gda.posterior(2, 0.1) is None and gda.predict(1, None) is False


def test_gda_needs_both_outcomes_and_adapts_gamma():
    gda = GDARule(gamma=0.5, delta_fp=0.1, delta_fn=0.3)
    gda.update(trace([0.1, 0.1]), failed=True)
    gda.update(trace([0.1, 0.2]), failed=True)
    assert gda.posterior(0, 0.1) is None  # no successful episode yet
    assert gda.predict(0, 0.1) is False
    gda.feedback("fn")
    assert gda.gamma == 0.5  # without statistics it could not have predicted: not blamed
    gda.update(trace([0.9, 0.9]), failed=False)
    gda.update(trace([0.8, 0.8]), failed=False)
    gda.reset()
    gda.predict(0, 0.85)
    gda.feedback("fp")
    assert gda.gamma == pytest.approx(0.6)
    gda.feedback("fn")
    assert gda.gamma == pytest.approx(0.3)
    for _ in range(5):
        gda.feedback("fn")
    assert gda.gamma == pytest.approx(0.01)
    restored = GDARule()
    restored.load_state_dict(gda.state_dict())
    assert restored.gamma == gda.gamma and restored.n_failed == 2


def test_gda_with_beta_needs_consecutive_steps():
    gda = GDARule(beta=2)
    for d, failed in ((0.1, True), (0.2, True), (0.9, False), (0.8, False)):
        gda.update(trace([d] * 4), failed)
    assert [gda.predict(t, 0.15) for t in range(3)] == [False, True, True]
    gda.feedback("fp")
    assert gda.beta.beta == 3 and gda.gamma == pytest.approx(0.52)
    gda.feedback("fn")
    assert gda.beta.beta == 1 and gda.gamma == pytest.approx(0.46)


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
    from shiftkit.policies.discriminator import Discriminator, DiscriminatorConfig
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
