"""VPACE/LfGP trainer core on a tiny point-mass env: smoke runs of every variant, shapes, exact resume,
reward-model signs, example loading and augmentation."""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.cpu_memory import keep_freed_memory
from shiftkit.policies.replay import ReplayBuffer
from shiftkit.policies.run_dir import load_checkpoint
from shiftkit.policies.sac import BatchedLinear, Intentions, NarrowProduct, polyak_update
from shiftkit.policies.trainers.vpace.args import VPACEArgs
from shiftkit.policies.trainers.vpace.example_buffer import (
    ExampleBuffer,
    ExampleRows,
    TaskExamples,
    load_dataset_examples,
)
from shiftkit.policies.trainers.vpace.reward_models import DACReward, SQILReward, rce_targets
from shiftkit.policies.trainers.vpace.schedulers import HANDCRAFTED_PRESETS, QTableScheduler, WeightedRandomScheduler
from shiftkit.policies.trainers.vpace.training import Agent, expert_transitions, make_env, train

GOAL = np.array([0.5, 0.5], np.float32)


class PointMass(gym.Env):
    """A point in the unit square moved by 0.1 * action; main task: reach GOAL; aux: get right (x > 0.8)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    observation_names = ("x", "y")
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.pos = self.np_random.uniform(-1.0, 0.0, 2).astype(np.float32)
        return self.pos.copy(), {}

    def step(self, action):
        self.pos = np.clip(self.pos + 0.1 * np.asarray(action, np.float32), -1.0, 1.0)
        success = bool(np.linalg.norm(self.pos - GOAL) < 0.1)
        return self.pos.copy(), float(success), False, False, {"is_success": success}


def point_examples(with_actions: bool = False) -> dict[str, TaskExamples]:
    rng = np.random.default_rng(0)
    main = GOAL + rng.uniform(-0.05, 0.05, (40, 2)).astype(np.float32)
    right = np.stack([rng.uniform(0.8, 1.0, 40), rng.uniform(-1.0, 1.0, 40)], 1).astype(np.float32)
    act = (lambda n: rng.uniform(-1, 1, (n, 2)).astype(np.float32)) if with_actions else (lambda n: None)
    return {"reach-goal": TaskExamples(main, act(40)), "go-right": TaskExamples(right, act(40))}


def tiny_args(tmp_path, name="run", **kw) -> VPACEArgs:
    base = dict(
        main_task="reach-goal",
        aux_tasks=["go-right"],
        output_dir=str(tmp_path / name),
        total_steps=300,
        buffer_warmup=100,
        random_steps=100,
        batch_size=16,
        example_batch_size=16,
        hidden=(16, 16),
        episode_steps=50,
        num_periods=2,
        eval_every=150,
        eval_episodes=2,
        checkpoint_every=100,
        log_every=50,
        env="point-mass",
        device="cpu",
        handcrafted=["main,go-right"],
        torch_threads=1,
    )
    variant = kw.pop("variant", "vpace")
    return VPACEArgs.for_variant(variant, **(base | kw))


def run(args, with_actions=False):
    return train(args, env_factory=lambda task: PointMass(), examples=point_examples(with_actions))


def final_state(out_dir):
    last = (out_dir / "checkpoints" / "last.txt").read_text().strip()
    return load_checkpoint(out_dir / "checkpoints" / last)


def test_vpace_smoke_run_writes_run_dir(tmp_path):
    metrics = run(tiny_args(tmp_path))
    out = tmp_path / "run"
    assert set(metrics) == {"success_rate", "env_return", "episodes"} and metrics["episodes"] == 2
    lines = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    train_lines = [x for x in lines if x["split"] == "train"]
    assert [x["step"] for x in lines if x["split"] == "eval"] == [150, 300]
    assert [x["step"] for x in train_lines] == [100, 150, 200, 250, 300]
    row = train_lines[-1]
    for key in ("critic_loss", "actor_loss", "alpha", "q_max", "q_min"):
        assert np.isfinite(row[f"{key}/reach-goal"]) and np.isfinite(row[f"{key}/go-right"])
    assert row["q_min/reach-goal"] == pytest.approx(-10.0, abs=1e-3)
    config = json.loads((out / "config.json").read_text())
    assert config["trainer"] == "vpace" and config["args"]["value_penalty"] == 10.0
    assert (out / "README.md").exists()
    state = final_state(out)
    assert state["step"] == 300 and state["replay"]["size"] == 300


def test_resume_gives_the_same_result(tmp_path):
    run(tiny_args(tmp_path, "straight"))
    run(tiny_args(tmp_path, "split", total_steps=200))
    run(tiny_args(tmp_path, "split", total_steps=300, resume=True))
    a, b = final_state(tmp_path / "straight"), final_state(tmp_path / "split")
    for key, value in a["agent"]["intentions"].items():
        assert torch.equal(value, b["agent"]["intentions"][key]), key
    metrics = lambda name: (tmp_path / name / "metrics.jsonl").read_text()  # noqa: E731
    assert metrics("straight") == metrics("split")


def test_best_checkpoint_holds_the_intentions_of_the_best_evaluation(tmp_path):
    from shiftkit.policies.trainers.vpace.training import load_policy

    run(tiny_args(tmp_path, "long", total_steps=400, eval_every=50, eval_episodes=3, seed=3))
    evals = [
        x
        for x in map(json.loads, (tmp_path / "long" / "metrics.jsonl").read_text().splitlines())
        if x["split"] == "eval"
    ]
    best = max(evals, key=lambda x: (x["success_rate"], x["env_return"], -x["step"]))
    assert best["step"] < 400  # the last evaluation is not the best one here, so best differs from last
    saved = load_checkpoint(tmp_path / "long" / "checkpoints" / "best.safetensors")
    assert saved["step"] == best["step"] and saved["eval"]["success_rate"] == best["success_rate"]
    # The same run stopped at that step ends with exactly these weights.
    run(tiny_args(tmp_path, "short", total_steps=best["step"], eval_every=50, eval_episodes=3, seed=3))
    for key, value in final_state(tmp_path / "short")["agent"]["intentions"].items():
        assert torch.equal(value, saved["agent"]["intentions"][key]), key
    card = json.loads((tmp_path / "long" / "card.json").read_text())
    assert card["best_eval/step"] == best["step"]
    # `shiftkit eval --policy RUN/checkpoints/best.safetensors` loads these weights.
    gym.register("point-mass", entry_point=PointMass, max_episode_steps=50)
    try:
        policy = load_policy(tmp_path / "long" / "checkpoints" / "best.safetensors")
    finally:
        gym.registry.pop("point-mass")
    for key, value in policy.agent.intentions.state_dict().items():
        assert torch.equal(value, saved["agent"]["intentions"][key]), key


def test_same_seed_same_bytes_other_seed_differs(tmp_path):
    run(tiny_args(tmp_path, "a", total_steps=150, eval_every=0))
    run(tiny_args(tmp_path, "b", total_steps=150, eval_every=0))
    run(tiny_args(tmp_path, "c", total_steps=150, eval_every=0, seed=1))
    sa, sb, sc = (final_state(tmp_path / n)["agent"]["intentions"]["actor.0.weight"] for n in "abc")
    assert torch.equal(sa, sb) and not torch.equal(sa, sc)


@pytest.mark.parametrize("variant", ["ace", "sqil", "vp-sqil", "dac", "rce", "lfgp"])
def test_variants_run(tmp_path, variant):
    args = tiny_args(tmp_path, variant=variant, total_steps=150, eval_every=150, n_step=1)
    if not args.multitask:
        args.handcrafted = []
    metrics = run(args, with_actions=variant == "lfgp")
    assert 0.0 <= metrics["success_rate"] <= 1.0
    lines = [json.loads(x) for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    last_train = [x for x in lines if x["split"] == "train"][-1]
    assert np.isfinite(last_train["critic_loss/reach-goal"])
    assert ("critic_loss/go-right" in last_train) == args.multitask
    assert ("discriminator_loss/reach-goal" in last_train) == (args.reward_model == "dac")


def test_n_step_run(tmp_path):
    assert "success_rate" in run(tiny_args(tmp_path, n_step=3, total_steps=150))


def test_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="variant"):
        VPACEArgs.for_variant("nope")
    with pytest.raises(ConfigError, match="value penalty"):
        run(tiny_args(tmp_path, variant="rce", value_penalty=10.0))
    with pytest.raises(ConfigError, match="unknown task"):
        run(tiny_args(tmp_path, "h", handcrafted=["main,lift"]))
    with pytest.raises(ConfigError, match="learned scheduler needs"):
        run(tiny_args(tmp_path, "q", scheduler="learned"))  # SQIL labels give the scheduler no signal
    with pytest.raises(ConfigError, match="vp_q_max must be one of mean, max, got 'median'"):
        run(tiny_args(tmp_path, "m", vp_q_max="median"))
    with pytest.raises(ConfigError, match="scheduler must be one of wrs, learned, got 'round-robin'"):
        run(tiny_args(tmp_path, "u", scheduler="round-robin"))
    with pytest.raises(ConfigError, match="unknown env"):
        make_env("no-such-env", "reach", {})
    bad = {
        "reach-goal": TaskExamples(np.zeros((5, 3), np.float32)),
        "go-right": TaskExamples(np.zeros((5, 3), np.float32)),
    }
    with pytest.raises(ConfigError, match="3-dim"):
        train(tiny_args(tmp_path, "d"), env_factory=lambda task: PointMass(), examples=bad)
    assert not any((tmp_path / r).exists() for r in ("h", "q", "m", "u", "d"))  # failed starts leave no run folder


@pytest.mark.parametrize("reduce", ["mean", "max"])
def test_q_max_is_the_mean_or_max_of_the_example_batch(tmp_path, reduce):
    args = tiny_args(tmp_path, vp_q_max=reduce, vp_filter_size=1)
    torch.manual_seed(0)
    agent = Agent(args, 2, PointMass.action_space, torch.device("cpu"))
    replay = ReplayBuffer(64, 2, 2)
    rng = np.random.default_rng(0)
    for t in range(64):
        replay.add(rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), episode_end=t % 8 == 7)
    examples = ExampleBuffer(point_examples(), args.tasks, aug_factor=0.0)
    stats = agent.update(replay.sample(rng, 16), examples.sample(rng, 32), None)
    # The first update's bound is this batch's reduction of min-twin Q(s*, a*); `q_examples` is its mean.
    if reduce == "mean":
        assert torch.equal(stats["q_max"], stats["q_examples"])
    else:
        assert torch.all(stats["q_max"] > stats["q_examples"])


def test_intentions_are_independent_per_task():
    torch.manual_seed(0)
    net = Intentions(num_tasks=3, obs_dim=4, act_dim=2, hidden=(8, 8))
    obs = torch.randn(3, 5, 4)
    h = net.encode(obs)
    act, logp = net.sample(h)
    assert act.shape == (3, 5, 2) and logp.shape == (3, 5) and act.abs().max() <= 1.0
    assert net.q(h, act).shape == (2, 3, 5)
    assert torch.equal(net.encode(obs[0]), obs[0].expand(3, 5, 4))  # shared rows, every task's
    # Task 1's loss leaves every other task's parameters untouched (no weight sharing, VPACE).
    net.q(h, act.detach())[:, 1].sum().backward()
    for p in net.critic.parameters():
        assert p.grad[[0, 2, 3, 5]].abs().sum() == 0 and p.grad[[1, 4]].abs().sum() > 0
    assert net.trunk is None and net.critic_parameters() == list(net.critic.parameters())


def reference_lfgp_parameter_count(tasks: int, obs: int, act: int, width: int = 256) -> int:
    """Parameters of utiasSTARS/lfgp's `MultiTaskFullyConnectedSquashedGaussianSAC` with shared layers
    and branched outputs (its default): trunk obs->w->w, per task a policy head w->w->2 act and two Q
    heads (w + act)->w->1 (grouped 1x1 convolutions), and a temperature per task."""
    trunk = (obs * width + width) + (width * width + width)
    policy = tasks * ((width * width + width) + (width * 2 * act + 2 * act))
    q = 2 * tasks * (((width + act) * width + width) + (width + 1))
    return trunk + policy + q + tasks


def test_lfgp_intentions_share_one_trunk_under_per_task_heads():
    # Thesis A.6 and the LfGP reference: one trunk for every task's policy and Q-functions, a small head
    # per task; the trunk is a critic parameter (trained by the critic loss, averaged into the target).
    args = VPACEArgs.for_variant("lfgp", main_task="stack", aux_tasks=["open", "close", "lift", "reach", "move"])
    agent = Agent(args, 59, gym.spaces.Box(-1.0, 1.0, (4,), np.float32), torch.device("cpu"))
    net = agent.intentions
    trainable = [p for p in net.parameters() if p.requires_grad]
    assert sum(p.numel() for p in trainable) == reference_lfgp_parameter_count(6, 59, 4)
    assert [tuple(p.shape) for p in net.trunk.parameters()] == [(256, 59), (256,), (256, 256), (256,)]
    assert [tuple(p.shape) for p in net.actor.parameters()] == [(6, 256, 256), (6, 1, 256), (6, 256, 8), (6, 1, 8)]
    assert [tuple(p.shape) for p in net.critic.parameters()] == [(12, 260, 256), (12, 1, 256), (12, 256, 1), (12, 1, 1)]
    trunk = set(map(id, net.trunk.parameters()))
    assert trunk <= set(map(id, net.critic_parameters())) and not trunk & set(map(id, net.actor_parameters()))
    opt_params = lambda opt: {id(p) for g in opt.param_groups for p in g["params"]}  # noqa: E731
    assert trunk <= opt_params(agent.critic_opt) and not trunk & opt_params(agent.actor_opt)
    # One task's Q loss reaches the trunk and that task's twin heads only.
    obs, act = torch.randn(7, 59), torch.rand(6, 7, 4)
    net.q(net.encode(obs), act)[:, 2].sum().backward()
    assert all(p.grad.abs().sum() > 0 for p in net.trunk.parameters())
    for p in net.critic.parameters():
        assert p.grad[[2, 8]].abs().sum() > 0 and p.grad[[i for i in range(12) if i not in (2, 8)]].abs().sum() == 0
    # The trunk is evaluated once per shared row: every task's heads read the same features.
    h = net.encode(obs)
    assert h.shape == (6, 7, 256) and h.stride(0) == 0
    # Polyak averaging moves the target trunk with the target Q heads.
    with torch.no_grad():
        for p in net.trunk.parameters():
            p.add_(1.0)
    before = [p.clone() for p in net.target_trunk.parameters()]
    polyak_update(net.target_pairs(), 0.5)
    for b, t, s in zip(before, net.target_trunk.parameters(), net.trunk.parameters(), strict=True):
        assert torch.allclose(t, 0.5 * b + 0.5 * s)
    # VPACE keeps SPEC 6.2's separate networks (its reference: `shared_layers: false`).
    assert VPACEArgs.for_variant("vpace", main_task="lift").shared_trunk is False


def record_grads_at_step(opt: torch.optim.Optimizer) -> list[list[torch.Tensor]]:
    """The gradients an optimizer steps with, recorded at each `step` call."""
    seen, step = [], opt.step

    def recording(*args, **kwargs):
        seen.append([p.grad.clone() for g in opt.param_groups for p in g["params"] if p.grad is not None])
        return step(*args, **kwargs)

    opt.step = recording
    return seen


@pytest.mark.parametrize("variant", ["vpace", "lfgp"])
def test_gradients_are_clipped_to_one_norm_over_all_tasks(variant):
    # The reference clips `clip_grad_norm_(qs_parameters, 10)` (and the policies' and temperatures'):
    # one norm over every task's parameters (both twins, and the trunk), not one per task.
    full = variant == "lfgp"
    args = VPACEArgs.for_variant(variant, main_task="m", aux_tasks=["a", "b"], hidden=(16, 16), max_grad_norm=1e-3)
    agent = Agent(args, 3, gym.spaces.Box(-1.0, 1.0, (2,), np.float32), torch.device("cpu"))
    rng = np.random.default_rng(0)
    replay = ReplayBuffer(64, 3, 2)
    for _ in range(64):
        replay.add(rng.standard_normal(3), rng.uniform(-1, 1, 2), rng.standard_normal(3), False)
    examples = {t: TaskExamples(rng.standard_normal((20, 3)).astype(np.float32)) for t in args.tasks}
    if full:
        examples = {t: TaskExamples(e.obs, rng.uniform(-1, 1, (20, 2)).astype(np.float32)) for t, e in examples.items()}
    buffer = ExampleBuffer(examples, args.tasks, 0.0)
    seen = {name: record_grads_at_step(getattr(agent, f"{name}_opt")) for name in ("critic", "actor", "alpha")}
    rows = None if full else buffer.sample(rng, 48)
    discriminator = (replay.sample(rng, 16), buffer.sample_discriminator(rng, 16)) if full else None
    agent.update(replay.sample(rng, 16), rows, discriminator)
    for name, [grads] in seen.items():
        total = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
        assert total == pytest.approx(1e-3, rel=1e-3), name
    # Every task keeps its share of the joint gradient (a per-task clip would equalise them).
    critic = dict(
        zip([id(p) for g in agent.critic_opt.param_groups for p in g["params"]], seen["critic"][0], strict=True)
    )
    weight = critic[id(agent.intentions.critic[0].weight)]
    per_member = weight.flatten(1).norm(dim=1)
    assert per_member.max() / per_member.min() > 1.5


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc settings")
def test_cpu_update_keeps_its_memory_instead_of_faulting_it_in_again():
    # A 5-intention update frees and reallocates megabyte tensors every step; handed back to the
    # kernel they cost about 1300 page faults (and 2-4 ms) per update (docs/vpace.md).
    keep_freed_memory()  # what `train` sets on CPU
    args = VPACEArgs.for_variant("vpace", main_task="m", aux_tasks=["a", "b", "c", "d"])
    agent = Agent(args, 59, gym.spaces.Box(-1.0, 1.0, (4,), np.float32), torch.device("cpu"))
    rng = np.random.default_rng(0)
    replay = ReplayBuffer(1000, 59, 4)
    for _ in range(1000):
        replay.add(rng.standard_normal(59), rng.uniform(-1, 1, 4), rng.standard_normal(59), False)
    rows = lambda: ExampleRows(rng.standard_normal((5, 128, 59), np.float32), None, np.ones((5, 128), np.float32))  # noqa: E731
    batches = [(replay.sample(rng, 128), rows()) for _ in range(3)]
    for batch, examples in batches * 2:  # the heap grows to the update's peak
        agent.update(batch, examples, None)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for batch, examples in batches * 2:
        agent.update(batch, examples, None)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 6 < 300


@pytest.mark.parametrize("out_dim", [1, 8])
def test_narrow_layers_compute_the_plain_product_and_its_gradients(out_dim):
    # Q's single output and the policy's 8 take NarrowProduct's layouts; value, gradients and the
    # gradients of gradients (DAC's gradient penalty) are those of x @ W + b.
    torch.manual_seed(0)
    x, weight, bias = (
        torch.randn(shape, dtype=torch.float64) for shape in ((3, 7, 5), (3, 5, out_dim), (3, 1, out_dim))
    )
    layer = BatchedLinear(3, 5, out_dim).double()
    with torch.no_grad():
        layer.weight.copy_(weight), layer.bias.copy_(bias)
    assert torch.allclose(layer(x), torch.baddbmm(bias, x, weight))
    inputs = tuple(t.clone().requires_grad_(True) for t in (x, weight, bias))
    assert torch.autograd.gradcheck(NarrowProduct.apply, inputs)
    assert torch.autograd.gradgradcheck(NarrowProduct.apply, inputs)


def test_first_layer_by_parts_is_the_product_of_the_concatenated_input():
    # The critic's first layer takes (observation, action) apart; value and gradients stay those of
    # the concatenated input.
    torch.manual_seed(0)
    layer = BatchedLinear(4, 7, 40).double()
    obs, act = torch.randn(4, 5, 5, dtype=torch.float64), torch.randn(4, 5, 2, dtype=torch.float64)
    results = []
    for by_parts in (True, False):
        a = act.clone().requires_grad_(True)
        layer.zero_grad()
        out = layer.forward_parts(obs, a) if by_parts else layer(torch.cat([obs, a], -1))
        out.square().sum().backward()
        results.append((out.detach(), a.grad, layer.weight.grad.clone(), layer.bias.grad.clone()))
    for by_parts, whole in zip(*results, strict=True):
        assert torch.allclose(by_parts, whole)


def test_weight_decay_does_not_collapse_a_critic_without_data_gradient():
    # Coupled L2 in Adam normalises the decay term to lr-sized steps and zeroes an idle critic within a
    # few thousand updates (it killed early Panda reach runs); decoupled decay shrinks by lr * wd per step.
    from shiftkit.policies.trainers.vpace.training import Agent

    args = VPACEArgs.for_variant("vpace", main_task="m", aux_tasks=["a"], hidden=(8, 8))
    agent = Agent(args, 3, gym.spaces.Box(-1.0, 1.0, (2,), np.float32), torch.device("cpu"))
    before = [p.detach().clone() for p in agent.intentions.critic.parameters()]
    for _ in range(2000):
        for p in agent.intentions.critic.parameters():
            p.grad = torch.zeros_like(p)
        agent.critic_opt.step()
    for p, p0 in zip(agent.intentions.critic.parameters(), before, strict=True):
        assert p.norm() / p0.norm() > 0.98


def test_reward_model_signs():
    sqil = SQILReward(num_tasks=2)
    x = torch.zeros(2, 3, 4)
    assert sqil.buffer_reward(x[0]).shape == (2, 3) and torch.all(sqil.buffer_reward(x[0]) == -1.0)
    assert torch.all(sqil.example_reward(x) == 1.0)

    torch.manual_seed(0)
    dac = DACReward(num_tasks=2, in_dim=2, hidden=(32, 32))
    opt = torch.optim.Adam(dac.parameters(), 1e-2)
    # Task 0's expert rows lie at +2, task 1's at -2; the buffer rows between them at 0.
    buffer_x, example_x = torch.randn(64, 2) * 0.3, torch.stack([torch.randn(64, 2) + 2.0, torch.randn(64, 2) - 2.0])
    for _ in range(150):
        opt.zero_grad()
        dac.loss(buffer_x, example_x)[0].backward()
        opt.step()
    assert torch.all(dac.example_reward(example_x).mean(-1) > 0) and torch.all(dac.buffer_reward(buffer_x).mean(-1) < 0)
    assert dac.buffer_reward(example_x[0])[0].mean() > 0 > dac.buffer_reward(example_x[0])[1].mean()  # own task only

    target, weight = rce_targets(torch.tensor([0.01, 0.5, 0.99]), gamma=0.99)
    assert torch.all((target > 0) & (target < 1)) and torch.all(target.diff() > 0) and torch.all(weight >= 1)


def test_discriminator_is_the_reference_multitask_network_and_loss():
    # One discriminator for all tasks (utiasSTARS/lfgp `ActionConditionedFullyConnectedDiscriminator`
    # with shared layers): in -> 256 -> 256 (tanh) -> one logit per task; the loss of its
    # `update_discriminator`, recomputed here step by step.
    torch.manual_seed(0)
    dac = DACReward(num_tasks=3, in_dim=5, hidden=(256, 256), gradient_penalty=10.0)
    linear = [m for m in dac.net if isinstance(m, torch.nn.Linear)]
    assert [tuple(m.weight.shape) for m in linear] == [(256, 5), (256, 256), (3, 256)]
    assert [type(m) for m in dac.net if not isinstance(m, torch.nn.Linear)] == [torch.nn.Tanh, torch.nn.Tanh]
    buffer_x, expert_x = torch.randn(8, 5), torch.randn(3, 8, 5)
    torch.manual_seed(1)
    loss, bce = dac.loss(buffer_x, expert_x)
    torch.manual_seed(1)
    mix = torch.rand(3, 8, 5)  # the same draw: a uniform weight per element
    logits = dac.net(buffer_x)  # (8, 3): every task's logit of the buffer rows, labelled 0
    own = torch.stack([dac.net(expert_x[t])[:, t] for t in range(3)])  # each task's rows, its own logit, 1
    bce_loss = torch.nn.BCEWithLogitsLoss()
    gan = (bce_loss(logits.reshape(-1), torch.zeros(24)) + bce_loss(own.reshape(-1), torch.ones(24))) / 2
    interp = (mix * buffer_x.expand(3, 8, 5) + (1 - mix) * expert_x).reshape(24, 5).requires_grad_(True)
    (grad,) = torch.autograd.grad(dac.net(interp), interp, torch.ones(24, 3))  # d(sum of all logits)/dx
    expected = gan + 10.0 * ((grad.norm(dim=-1) - 1) ** 2).mean()
    assert loss.item() == pytest.approx(expected.item(), rel=1e-5)
    assert bce.mean().item() == pytest.approx(gan.item(), rel=1e-5)
    assert torch.equal(dac.buffer_reward(buffer_x), logits.detach().T) and torch.allclose(
        dac.example_reward(expert_x), own
    )


def test_lfgp_preset_is_thesis_table_a2():
    args = VPACEArgs.for_variant("lfgp", main_task="stack")
    table = dict(
        batch_size=256, actor_lr=1e-5, lr=3e-4, polyak=1e-4, buffer_warmup=25_000, random_steps=50_000,
        initial_alpha=1e-2, max_grad_norm=10.0, weight_decay=1e-2, gamma=0.99, gradient_penalty=10.0,
        expert_sample_rate=0.1, expert_sample_decay=0.99999, final_pair_bias=0.95, reward_scale=1.0,
        shared_trunk=True, reward_model="dac", full_trajectories=True,
    )  # fmt: skip
    assert {k: getattr(args, k) for k in table} == table
    vpace = VPACEArgs.for_variant("vpace", main_task="lift")  # Table B.2
    assert (vpace.actor_lr, vpace.polyak, vpace.buffer_warmup, vpace.random_steps, vpace.batch_size) == (
        3e-4, 1e-3, 5_000, 10_000, 128,
    )  # fmt: skip
    # The expert share of a batch decays per update, the reference's rounding down.
    assert [expert_transitions(args, 25_000 + k) for k in (0, 99_999, 229_999, 399_999)] == [25, 9, 2, 0]


def test_example_rows_divide_the_batch_among_the_tasks_as_the_reference():
    # The reference's `fraction` sampling: batch 256 = 128 replay + 128 expert rows, the latter
    # divided among the tasks (the main task gets the remainder); a task's critic counts its own rows.
    sets = {t: TaskExamples(np.full((10, 2), i, np.float32)) for i, t in enumerate(["main", "a", "b"])}
    buffer = ExampleBuffer(sets, ["main", "a", "b"], aug_factor=0.0)
    assert buffer.split(128).tolist() == [44, 42, 42]
    rows = buffer.sample(np.random.default_rng(0), 128)
    assert rows.obs.shape == (3, 44, 2) and rows.weight.sum(1).tolist() == [44, 42, 42]
    assert all(np.all(rows.obs[t] == t) for t in range(3))
    four = ExampleBuffer({**sets, "c": sets["a"]}, ["main", "a", "b", "c"])
    assert four.split(128).tolist() == [32, 32, 32, 32]


def test_padding_rows_do_not_change_the_update(tmp_path):
    # Tasks with a smaller share pad their block; padded rows weigh nothing.
    args = tiny_args(tmp_path, aux_tasks=["go-right", "x"])
    replay = ReplayBuffer(64, 2, 2)
    rng = np.random.default_rng(0)
    for _ in range(64):
        replay.add(rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), rng.uniform(-1, 1, 2), False)
    batch = replay.sample(rng, 16)
    rows = ExampleBuffer({**point_examples(), "x": point_examples()["go-right"]}, args.tasks, 0.0).sample(rng, 32)
    assert rows.weight.sum(1).tolist() == [12, 10, 10]
    results = []
    for fill in (0.0, 100.0):
        obs = rows.obs.copy()
        obs[rows.weight == 0] = fill
        torch.manual_seed(0)
        agent = Agent(args, 2, PointMass.action_space, torch.device("cpu"))
        torch.manual_seed(1)
        agent.update(batch, ExampleRows(obs, None, rows.weight), None)
        results.append([p.detach().clone() for p in agent.intentions.parameters()])
    for a, b in zip(*results, strict=True):
        assert torch.allclose(a, b, atol=1e-6)


def test_expert_rows_for_the_discriminator_and_the_batch():
    rng = np.random.default_rng(0)
    obs = np.arange(20, dtype=np.float32).reshape(10, 2)
    final = np.zeros(10, bool)
    final[[4, 9]] = True
    nxt = np.roll(obs, -1, 0)
    nxt[final] = obs[final]
    buffer = ExampleBuffer({"t": TaskExamples(obs, np.ones((10, 1), np.float32), nxt, final)}, ["t"], 0.0)
    rows = buffer.sample_discriminator(rng, 200, final_bias=0.95)
    ends = np.isin(rows.obs[0, :, 0], obs[final, 0])
    assert rows.obs.shape == (1, 200, 2) and ends.sum() == 190  # 95 % (s_T, 0) / last rows
    o, a, n = buffer.sample_transitions(rng, 50)
    index = (o[:, 0] / 2).astype(int)
    assert np.array_equal(n, nxt[index]) and a.shape == (50, 1)


def test_lift_and_stack_studies_use_the_reference_task_sets_and_budgets():
    # utiasSTARS/vpace env_default_configs.py at 5 Hz: lift `expert_filenames = 0_stack-open,1_close,
    # 3_lift,4_reach`, max_steps 200000; stack `0_stack-open,1_close,2_stack,3_lift,4_reach,5_move`,
    # 500000 (the thesis' 2M at 20 Hz in robot time).
    import importlib
    import tomllib

    repo = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(repo / "bench" / "science"))
    try:
        study = importlib.import_module("vpace_lfgp")
    finally:
        sys.path.remove(str(repo / "bench" / "science"))
    assert sorted(study.EXAMPLE_TASKS) == ["close", "lift", "open", "reach"] and study.EXAMPLE_TASKS[0] == "lift"
    assert sorted(study.LFGP_TASKS["stack"]) == ["close", "lift", "move-object", "open", "reach", "stack"]
    assert (study.LIFT_STEPS, study.STACK_STEPS) == (200_000, 500_000)
    pipeline = tomllib.loads((repo / "docs" / "pipelines" / "vpace_lift_examples.toml").read_text())
    sources = sorted(Path(s["path"]).name.removeprefix("example-src-") for s in pipeline["sources"])
    assert sources == sorted(study.EXAMPLE_TASKS)


def test_replay_n_step_stops_at_episode_end():
    buf = ReplayBuffer(capacity=10, obs_dim=1, act_dim=1)
    for t in range(6):
        buf.add(np.array([t]), np.zeros(1), np.array([t + 1]), episode_end=t == 2)
    rng = np.random.default_rng(0)
    s = buf.sample(rng, 200, n_step=3)
    start = s.obs[:, 0].astype(int)
    expected_steps = np.array([3, 2, 1, 3, 2, 1])[start]
    assert np.array_equal(s.steps, expected_steps)
    assert np.array_equal(s.next_obs[:, 0], start + expected_steps)


def test_example_augmentation_keeps_constant_dims_exact():
    rng = np.random.default_rng(0)
    obs = np.stack([rng.normal(0, 2.0, 5000), np.full(5000, 0.3)], 1).astype(np.float32)
    buf = ExampleBuffer({"t": TaskExamples(obs)}, ["t"], aug_factor=0.1)
    a = np.random.default_rng(1)
    sampled = buf.sample(a, 5000).obs
    assert np.all(sampled[0, :, 1] == np.float32(0.3))
    idx = np.random.default_rng(1).integers(0, 5000, 5000)
    noise = sampled[0, :, 0] - obs[idx, 0]
    assert noise.std() == pytest.approx(0.1 * obs[:, 0].std(), rel=0.1)


def test_scheduler_rates_and_handcrafted():
    s = WeightedRandomScheduler(["main-task", "a", "b"], num_periods=4, main_rate=0.5, handcraft_rate=0.0)
    rng = np.random.default_rng(0)
    picks = np.array([s.plan_episode(rng) for _ in range(2000)]).ravel()
    assert np.mean(picks == 0) == pytest.approx(0.5, abs=0.03) and np.mean(picks == 1) == pytest.approx(0.25, abs=0.03)
    h = WeightedRandomScheduler(["m", "a"], 2, handcraft_rate=1.0, handcrafted=["a,main"])
    assert h.plan_episode(rng) == [1, 0]


def test_handcrafted_presets_expand_to_the_thesis_sequences():
    tasks = ["stack", "reach", "grasp", "lift", "open"]
    s = WeightedRandomScheduler(tasks, 8, handcraft_rate=1.0, handcrafted=["panda"])
    assert len(s.sequences) == len(HANDCRAFTED_PRESETS["panda"]) == 3
    assert s.sequences[0] == [1, 3, 0, 4, 1, 3, 0, 4]  # reach, lift, main, open, ...
    with pytest.raises(ConfigError, match=r"unknown task\(s\) \['move-object'\]"):
        WeightedRandomScheduler(tasks, 8, handcrafted=["panda-lfgp"])


def test_learned_scheduler_prefers_the_plan_with_the_higher_main_return():
    # Two periods of 3 steps; main-task reward 1 per step only when task 1 runs in the first period.
    s = QTableScheduler(
        ["main", "aux"],
        num_periods=2,
        gamma=0.9,
        temperature=1.0,
        temperature_min=0.05,
        temperature_decay=0.99,
        handcraft_rate=0.0,
    )
    rng = np.random.default_rng(0)
    for _ in range(300):
        plan = s.plan_episode(rng)
        s.update(plan, np.full(6, float(plan[0] == 1)), period=3)
    q0 = s.q_values([])
    assert q0[1] == pytest.approx(sum(0.9**t for t in range(6)), rel=1e-3) and q0[0] == pytest.approx(0.0, abs=1e-3)
    picks = [s.plan_episode(rng)[0] for _ in range(200)]
    assert np.mean(np.array(picks) == 1) > 0.95
    restored = QTableScheduler(["main", "aux"], 2, 0.9)
    restored.load_state_dict(s.state_dict())
    assert restored.temperature == s.temperature and np.array_equal(restored.q_values([1]), s.q_values([1]))


def test_learned_scheduler_run_resumes_exactly(tmp_path):
    kw = dict(variant="dac", multitask=True, scheduler="learned", eval_every=0)
    run(tiny_args(tmp_path, "straight", total_steps=300, **kw))
    run(tiny_args(tmp_path, "split", total_steps=200, **kw))
    run(tiny_args(tmp_path, "split", total_steps=300, resume=True, **kw))
    a, b = final_state(tmp_path / "straight"), final_state(tmp_path / "split")
    assert a["scheduler"]["table"] and a["scheduler"]["temperature"] < 360.0
    assert a["scheduler"]["table"].keys() == b["scheduler"]["table"].keys()
    assert all(np.array_equal(v, b["scheduler"]["table"][k]) for k, v in a["scheduler"]["table"].items())
    assert torch.equal(a["agent"]["intentions"]["actor.0.weight"], b["agent"]["intentions"]["actor.0.weight"])


def test_examples_from_lerobot_dataset(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    features = {
        "observation.state": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]},
        "observation.environment_state": {"dtype": "float32", "shape": (1,), "names": ["z"]},
        "action": {"dtype": "float32", "shape": (2,), "names": ["dx", "dy"]},
    }
    root = tmp_path / "examples"
    ds = LeRobotDataset.create("test/examples", fps=5, features=features, root=root, use_videos=False)
    for ep, task in enumerate(["reach-goal", "go-right", "reach-goal"]):
        for i in range(3):
            ds.add_frame(
                {
                    "observation.state": np.array([ep, i], np.float32),
                    "observation.environment_state": np.array([7], np.float32),
                    "action": np.ones(2, np.float32),
                    "task": task,
                }
            )
        ds.save_episode()
    ds.finalize()

    examples, sources = load_dataset_examples([str(root)], ["reach-goal", "go-right"])
    assert examples["reach-goal"].obs.shape == (6, 3) and examples["go-right"].obs.shape == (3, 3)
    assert set(examples["reach-goal"].obs[:, 0]) == {0.0, 2.0} and np.all(examples["go-right"].obs[:, 2] == 7)
    assert sources[0].fingerprint
    traj, _ = load_dataset_examples([str(root)], ["reach-goal"], with_actions=True)
    # 6 frames + one (s_T, 0) pair per episode; next states within an episode, the last row and its
    # (s_T, 0) pair transition to themselves and end the demonstration
    t = traj["reach-goal"]
    assert t.obs.shape == (8, 3) and np.all(t.act[-2:] == 0)
    assert t.next_obs[:, 1].tolist() == [1, 2, 2, 1, 2, 2, 2, 2] and t.final.tolist() == [0, 0, 1, 0, 0, 1, 1, 1]


def test_cli_train_and_plot(tmp_path, monkeypatch):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from shiftkit.app.cli import main

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    if "ShiftkitTestPointMass-v0" not in gym.registry:
        gym.register("ShiftkitTestPointMass-v0", entry_point=PointMass, max_episode_steps=50)
    features = {"observation.state": {"dtype": "float32", "shape": (2,), "names": ["x", "y"]}}
    root = tmp_path / "point_examples"
    ds = LeRobotDataset.create("test/point_examples", fps=5, features=features, root=root, use_videos=False)
    for task, ex in point_examples().items():
        for row in ex.obs[:10]:
            ds.add_frame({"observation.state": row, "task": task})
        ds.save_episode()
    ds.finalize()

    common = [
        "--examples",
        str(root),
        "--env",
        "ShiftkitTestPointMass-v0",
        "--main-task",
        "reach-goal",
        "--total-steps",
        "150",
        "--buffer-warmup",
        "50",
        "--random-steps",
        "50",
        "--batch-size",
        "8",
        "--example-batch-size",
        "8",
        "--hidden",
        "8,8",
        "--num-periods",
        "2",
        "--eval-every",
        "75",
        "--eval-episodes",
        "1",
        "--threads",
        "1",
        "--device",
        "cpu",
    ]
    for seed in ("0", "1"):
        out = tmp_path / f"vpace{seed}"
        assert (
            main(
                [
                    "train",
                    "vpace",
                    *common,
                    "--aux-tasks",
                    "go-right",
                    "--handcrafted",
                    "main,go-right",
                    "--output",
                    str(out),
                    "--seed",
                    seed,
                ]
            )
            == 0
        )
    config = json.loads((tmp_path / "vpace0" / "config.json").read_text())
    assert config["args"]["aux_tasks"] == ["go-right"] and config["args"]["value_penalty"] == 10.0
    assert config["args"]["total_steps"] == 150 and config["datasets"][0]["fingerprint"]
    assert main(["train", "vpace", *common, "--variant", "sqil", "--output", str(tmp_path / "sqil")]) == 0
    assert json.loads((tmp_path / "sqil" / "config.json").read_text())["args"]["multitask"] is False

    # User mistakes: one line, exit 2.
    assert (
        main(
            ["train", "vpace", *common, "--variant", "rce", "--value-penalty", "10", "--output", str(tmp_path / "bad")]
        )
        == 2
    )
    assert main(["train", "vpace", *common, "--aux-tasks", "lift", "--output", str(tmp_path / "bad2")]) == 2

    png = tmp_path / "curves.png"
    groups = [f"vpace={tmp_path / 'vpace0'},{tmp_path / 'vpace1'}", f"sqil={tmp_path / 'sqil'}"]
    assert main(["plot", "curves", *groups, "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_iqm_and_stratified_bootstrap():
    from shiftkit.policies.curves import iqm, stratified_bootstrap_ci

    assert iqm(np.array([0.0, 1.0, 2.0, 3.0, 100.0, 5.0, 6.0, 7.0])) == pytest.approx(np.mean([2, 3, 5, 6]))
    scores = np.array([[0.0, 0.2], [0.0, 0.4], [1.0, 0.6], [1.0, 0.8]])
    low, high = stratified_bootstrap_ci(scores, np.array(["a", "a", "b", "b"]), reps=500)
    assert np.all(low <= iqm(scores, axis=0)) and np.all(iqm(scores, axis=0) <= high)
    # Stratification: every resample keeps two runs of task a (score 0) and two of task b (score 1),
    # so the IQM of the first column is exactly 0.5 in every resample.
    assert low[0] == pytest.approx(0.5) and high[0] == pytest.approx(0.5)
    assert low[1] < high[1]


PUBLISHED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "vpace"


@pytest.mark.skipif(not PUBLISHED.is_dir(), reason=f"published VPACE data not found at {PUBLISHED}")
def test_panda_run_from_imported_examples_evaluates_with_shiftkit_eval(tmp_path, capsys):
    """Published examples -> `shiftkit import vpace` -> `train vpace` on Panda reach -> `shiftkit eval`."""
    from shiftkit.app.cli import main

    assert (
        main(
            [
                "import",
                "vpace",
                str(PUBLISHED / "examples_1200_4_reach.gz"),
                "--repo-id",
                "test/reach-ex",
                "--root",
                str(tmp_path / "ex"),
            ]
        )
        == 0
    )
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "vpace",
                "--examples",
                str(tmp_path / "ex"),
                "--env",
                "panda-play",
                "--main-task",
                "reach",
                "--variant",
                "sqil",
                "--total-steps",
                "60",
                "--buffer-warmup",
                "30",
                "--random-steps",
                "30",
                "--batch-size",
                "8",
                "--example-batch-size",
                "8",
                "--hidden",
                "16,16",
                "--eval-every",
                "0",
                "--threads",
                "1",
                "--device",
                "cpu",
                "--output",
                str(run),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "eval",
                "--policy",
                str(run),
                "--env",
                "panda-play",
                "--task",
                "reach",
                "--episodes",
                "1",
                "--seed",
                "5",
                "--out",
                str(tmp_path / "eval.json"),
            ]
        )
        == 0
    )
    assert "success" in capsys.readouterr().out
