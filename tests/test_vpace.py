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
from shiftkit.policies.example_buffer import ExampleBuffer, TaskExamples, load_dataset_examples
from shiftkit.policies.replay import ReplayBuffer
from shiftkit.policies.reward_models import DACReward, SQILReward, rce_targets
from shiftkit.policies.run_dir import load_checkpoint
from shiftkit.policies.sac import BatchedLinear, Intentions, NarrowProduct, clip_grad_norm_per_member
from shiftkit.policies.schedulers import HANDCRAFTED_PRESETS, QTableScheduler, WeightedRandomScheduler
from shiftkit.policies.trainers.vpace.args import VPACEArgs
from shiftkit.policies.trainers.vpace.training import Agent, make_env, train

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
    with pytest.raises(ConfigError, match="unknown vp_q_max"):
        run(tiny_args(tmp_path, "m", vp_q_max="median"))
    with pytest.raises(ConfigError, match="unknown scheduler"):
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
    stats = agent.update(replay.sample(rng, 16), *examples.sample(rng, 16))
    # The first update's bound is this batch's reduction of min-twin Q(s*, a*); `q_examples` is its mean.
    if reduce == "mean":
        assert torch.equal(stats["q_max"], stats["q_examples"])
    else:
        assert torch.all(stats["q_max"] > stats["q_examples"])


def test_intentions_are_independent_per_task():
    torch.manual_seed(0)
    net = Intentions(num_tasks=3, obs_dim=4, act_dim=2, hidden=(8, 8))
    obs = torch.randn(3, 5, 4)
    act, logp = net.sample(obs)
    assert act.shape == (3, 5, 2) and logp.shape == (3, 5) and act.abs().max() <= 1.0
    assert net.q(obs, act).shape == (2, 3, 5)
    # Task 1's loss leaves every other task's parameters untouched (no weight sharing).
    net.q(obs, act.detach())[:, 1].sum().backward()
    for p in net.critic.parameters():
        assert p.grad[[0, 2, 3, 5]].abs().sum() == 0 and p.grad[[1, 4]].abs().sum() > 0
    # Per-member clipping scales each member to the bound separately.
    norms = clip_grad_norm_per_member(net.critic.parameters(), max_norm=1e-3)
    after = torch.stack([p.grad.flatten(1).square().sum(1) for p in net.critic.parameters()]).sum(0).sqrt()
    assert torch.allclose(after[[1, 4]], torch.full((2,), 1e-3), rtol=1e-3) and norms[0] == 0


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
    batches = [(replay.sample(rng, 128), rng.standard_normal((5, 128, 59), np.float32)) for _ in range(3)]
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
    sqil = SQILReward()
    x = torch.zeros(2, 3, 4)
    assert torch.all(sqil.buffer_reward(x) == -1.0) and torch.all(sqil.example_reward(x) == 1.0)

    torch.manual_seed(0)
    dac = DACReward(num_tasks=2, in_dim=2, hidden=(32, 32))
    opt = torch.optim.Adam(dac.parameters(), 1e-2)
    buffer_x, example_x = torch.randn(2, 64, 2) - 2.0, torch.randn(2, 64, 2) + 2.0
    for _ in range(100):
        opt.zero_grad()
        dac.loss(buffer_x, example_x).sum().backward()
        opt.step()
    assert torch.all(dac.example_reward(example_x).mean(-1) > 0) and torch.all(dac.buffer_reward(buffer_x).mean(-1) < 0)

    target, weight = rce_targets(torch.tensor([0.01, 0.5, 0.99]), gamma=0.99)
    assert torch.all((target > 0) & (target < 1)) and torch.all(target.diff() > 0) and torch.all(weight >= 1)


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
    sampled, _ = buf.sample(a, 5000)
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
    # 6 frames + one (s_T, 0) pair per episode
    assert traj["reach-goal"].obs.shape == (8, 3) and np.all(traj["reach-goal"].act[-2:] == 0)


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
