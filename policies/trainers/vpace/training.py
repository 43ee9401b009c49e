"""VPACE / LfGP trainer: scheduled auxiliary control (SAC-X) learning from success examples (thesis ch. 6-7, docs/vpace.md).

One SAC intention per task (main + auxiliary), all learning off-policy from one shared replay buffer of
every interaction; a scheduler picks which intention acts in each fixed period of an episode. Rewards
come from a reward model (SQIL labels, a DAC discriminator, or RCE's classifier critic); value
penalization keeps Q inside [Q_min, Q_max]. At test time only the main intention runs (mean action).

Variants (`--variant`) are presets of three switches, any of which can be overridden:
    vpace   SQIL, all tasks, VP          ace     SQIL, all tasks, no VP
    vp-sqil SQIL, main task only, VP     sqil    SQIL, main task only, no VP
    dac     DAC, main task only          rce     RCE, main task only
    lfgp    DAC on (s, a) from full expert trajectories, all tasks, thesis Table A.2 and the
            reference's shared-trunk network; expert transitions enter the batch instead of examples

The loop below reads top to bottom: set-up, then per episode a scheduler plan, per step act, store and
update, with periodic evaluation, metrics and resumable checkpoints (written at episode ends, where the
state to restore is only models, optimizers, buffer and random generators: each episode's environment
reset is seeded by the run seed and the episode number). The intentions at the best periodic evaluation
are also kept (checkpoints/best.safetensors): a policy that solved the task can lose it with further training
(docs/vpace.md), and the best evaluation picks the snapshot to deploy, the way early stopping does.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from shiftkit.datasets.dataset import Dataset
from shiftkit.datasets.errors import ConfigError
from shiftkit.policies.cpu_memory import keep_freed_memory
from shiftkit.policies.replay import ReplayBuffer, ReplaySample
from shiftkit.policies.sac import Intentions, polyak_update
from shiftkit.policies.trainers.vpace.args import VPACEArgs
from shiftkit.policies.trainers.vpace.example_buffer import (
    STATE_KEYS,
    ExampleBuffer,
    ExampleRows,
    TaskExamples,
    load_dataset_examples,
)
from shiftkit.policies.trainers.vpace.reward_models import DACReward, SQILReward, rce_loss, rce_targets
from shiftkit.policies.trainers.vpace.schedulers import QTableScheduler, WeightedRandomScheduler
from shiftkit.policies.trainers.vpace.value_penalty import ValueBounds, value_penalty

EVAL_SEED_OFFSET = 1_000_003  # evaluation episodes never reuse a training reset seed


# ---------------------------------------------------------------------------------------------------
# Environment glue (gymnasium API; success from info["is_success"])


def make_env(name: str, task: str, env_kwargs: dict[str, Any]) -> gym.Env:
    """A registered gymnasium id as is; otherwise `shiftkit.envs.make(name, task, **kw)`."""
    from shiftkit.envs import families, make

    families()  # shiftkit's families register their gymnasium ids when first asked for
    if name in gym.registry:
        return gym.make(name, **env_kwargs)
    try:
        return make(name, task, **env_kwargs)
    except ValueError as exc:  # unknown env/task names
        raise ConfigError(str(exc)) from None


def flat_obs(obs: Any) -> np.ndarray:
    """Vector observation; dict observations concatenate the LeRobot state keys, like the examples."""
    if isinstance(obs, dict):
        obs = np.concatenate([np.ravel(obs[k]) for k in STATE_KEYS if k in obs])
    return np.asarray(obs, np.float32).ravel()


def improves(result: dict[str, float], best: dict[str, float]) -> bool:
    """Whether an evaluation beats the best so far: higher success rate, then higher return."""
    return not best or (result["success_rate"], result["env_return"]) > (best["success_rate"], best["env_return"])


def expert_transitions(args: VPACEArgs, step: int) -> int:
    """Expert transitions in the batch of the update at interaction `step` (LfGP, thesis Table A.2: a
    share `expert_sample_rate` of the batch, times `expert_sample_decay` per update; the reference
    decays the rate before each update and rounds the rows down)."""
    rate = args.expert_sample_rate * args.expert_sample_decay ** (step - args.buffer_warmup + 1)
    return int(rate * args.batch_size)


def sample_update(
    args: VPACEArgs, step: int, replay: ReplayBuffer, examples: ExampleBuffer, rng: np.random.Generator
) -> tuple[ReplaySample, ExampleRows | None, tuple[ReplaySample, ExampleRows] | None]:
    """The data of the update at interaction `step`, `Agent.update`'s arguments: the replay batch (with
    LfGP's expert transitions in it), each task's example rows for its critic (success examples) and,
    for a learned reward, the discriminator's own replay rows and each task's expert rows (the
    reference samples the discriminator's batch apart from the critic's)."""
    n_expert = expert_transitions(args, step)
    batch = replay.sample(rng, args.batch_size - n_expert, args.n_step)
    if n_expert:
        batch = batch.extended(*examples.sample_transitions(rng, n_expert))
    example_rows = None if args.full_trajectories else examples.sample(rng, args.example_batch_size)
    discriminator = None
    if args.reward_model == "dac":
        discriminator = (
            replay.sample(rng, args.batch_size),
            examples.sample_discriminator(rng, args.batch_size, args.final_pair_bias),
        )
    return batch, example_rows, discriminator


def evaluate(agent: Agent, env: gym.Env, episodes: int, horizon: int, seed: int) -> dict[str, float]:
    """Main intention, mean action; an episode succeeds if the env ever reports `is_success`."""
    successes, returns = [], []
    for i in range(episodes):
        obs, _ = env.reset(seed=seed + i)
        success, ret = False, 0.0
        for _ in range(horizon):
            obs, reward, terminated, truncated, info = env.step(agent.env_action(agent.act(flat_obs(obs), 0, True)))
            success |= bool(info.get("is_success", False))
            ret += float(reward)
            if terminated or truncated:
                break
        successes.append(success)
        returns.append(ret)
    return {"success_rate": float(np.mean(successes)), "env_return": float(np.mean(returns)), "episodes": episodes}


# ---------------------------------------------------------------------------------------------------
# The learner: intentions, reward model, value bounds and their optimizers


class Agent:
    """Everything that learns, plus one update step over all intentions at once."""

    def __init__(self, args: VPACEArgs, obs_dim: int, action_space: gym.spaces.Box, device: torch.device):
        self.args, self.device = args, device
        self.num_tasks = len(args.tasks)
        act_dim = int(np.prod(action_space.shape))
        self.action_low, self.action_high = action_space.low.astype(np.float32), action_space.high.astype(np.float32)
        self.target_entropy = -float(act_dim)
        self.intentions = Intentions(
            self.num_tasks, obs_dim, act_dim, args.hidden, args.initial_alpha, args.shared_trunk
        ).to(device)
        # One fused kernel per parameter instead of a dozen element-wise passes: the default (for-loop)
        # AdamW on CPU took about 8 % of a profiled update; fused is the same rule.
        fused = device.type in ("cpu", "cuda")

        def adamw(params: Any, lr: float) -> torch.optim.AdamW:
            return torch.optim.AdamW(params, lr, weight_decay=args.weight_decay, fused=fused)

        self.actor_opt = adamw(self.intentions.actor_parameters(), args.actor_lr)
        self.critic_opt = adamw(self.intentions.critic_parameters(), args.lr)
        self.alpha_opt = torch.optim.Adam([self.intentions.log_alpha], args.lr, fused=fused)
        if args.reward_model == "dac":
            in_dim = obs_dim + (act_dim if args.full_trajectories else 0)
            self.reward = DACReward(self.num_tasks, in_dim, args.hidden, args.gradient_penalty).to(device)
            self.reward_opt = adamw(self.reward.parameters(), args.lr)
        else:
            self.reward = SQILReward(self.num_tasks)
        self.bounds = ValueBounds(self.num_tasks, args.reward_scale, args.gamma, args.vp_filter_size)

    # -- acting -------------------------------------------------------------------------------------

    @torch.no_grad()
    def act(self, obs: np.ndarray, task: int, deterministic: bool = False) -> np.ndarray:
        """Action in [-1, 1] of intention `task` (all intentions run batched; one is kept)."""
        h = self.intentions.encode(torch.as_tensor(obs, device=self.device).unsqueeze(0))
        action = self.intentions.mean_action(h) if deterministic else self.intentions.sample(h)[0]
        return action[task, 0].cpu().numpy()

    @torch.no_grad()
    def main_task_rewards(self, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
        """Scaled learned reward of the main task for an episode's (L, ·) states (and actions for LfGP)."""
        x = torch.as_tensor(np.concatenate([obs, act], -1) if self.args.full_trajectories else obs, device=self.device)
        return (self.args.reward_scale * self.reward.buffer_reward(x)[0]).cpu().numpy()

    def env_action(self, action: np.ndarray) -> np.ndarray:
        """Map [-1, 1] to the environment's action bounds."""
        return self.action_low + (action + 1.0) * 0.5 * (self.action_high - self.action_low)

    # -- learning -----------------------------------------------------------------------------------

    def update(
        self,
        batch: ReplaySample,
        examples: ExampleRows | None,
        discriminator: tuple[ReplaySample, ExampleRows] | None = None,
    ) -> dict:
        """One gradient step of every intention (and the discriminator) on one replay batch shared by all
        tasks, each task's own example rows for its critic (`examples`: success examples; None with full
        trajectories) and, for a learned reward, the discriminator's replay rows and each task's expert
        rows (`discriminator`)."""
        a, T, dev = self.args, self.num_tasks, self.device
        tensor = lambda x: torch.as_tensor(x, device=dev)  # noqa: E731
        obs, act, next_obs = tensor(batch.obs), tensor(batch.act), tensor(batch.next_obs)  # (B, ·), every task's
        stats: dict[str, torch.Tensor] = {}

        # Reward model: train the discriminator (the reference clips no gradient here), then score the
        # batch (SQIL: fixed labels).
        if self.reward.learned and discriminator is not None:
            replay_rows, expert = discriminator
            buffer_x, expert_x = tensor(replay_rows.obs), tensor(expert.obs)
            if a.full_trajectories:
                buffer_x = torch.cat([buffer_x, tensor(replay_rows.act)], -1)
                expert_x = torch.cat([expert_x, tensor(expert.act)], -1)
            d_loss, stats["discriminator_loss"] = self.reward.loss(buffer_x, expert_x)
            self.reward_opt.zero_grad(set_to_none=True)
            d_loss.backward()
            self.reward_opt.step()
        if a.full_trajectories:
            step_rewards = self.reward.buffer_reward(torch.cat([obs, act], -1)).unsqueeze(-1)  # (T, B, 1)
        else:
            step_rewards = self.reward.buffer_reward(tensor(batch.reward_obs))  # (T, B, n)
        steps = tensor(batch.steps)
        n = step_rewards.shape[-1]
        discounts = a.gamma ** torch.arange(n, device=dev, dtype=torch.float32)
        valid = (torch.arange(n, device=dev) < steps.unsqueeze(-1)).float()  # (B, n)
        buffer_reward = a.reward_scale * (step_rewards * discounts * valid).sum(-1)  # (T, B)
        bootstrap_discount = a.gamma ** steps.float()  # (B,)

        # Critic targets: buffer rows bootstrap from s'; each task's example rows transition to
        # themselves. Rows go through each network in one pass (one batched matmul per layer); a
        # shared trunk sees each replay row once.
        if examples is None:  # full trajectories: no example rows (padding of width 0)
            ex_obs, ex_weight = obs.new_zeros(T, 0, obs.shape[-1]), obs.new_zeros(T, 0)
        else:
            ex_obs, ex_weight = tensor(examples.obs), tensor(examples.weight)
        rows = [obs.shape[0], ex_obs.shape[1]]
        encode = self.intentions.encode
        h = torch.cat([encode(obs), encode(ex_obs)], 1)  # with gradient: the critic loss trains a trunk
        alpha = self.intentions.alpha.detach().unsqueeze(-1)  # (T, 1)
        with torch.no_grad():
            next_and_ex_act, next_and_ex_logp = self.intentions.sample(
                torch.cat([encode(next_obs), h[:, rows[0] :]], 1)
            )
            ex_act = next_and_ex_act[:, rows[0] :]  # a* ~ pi(s*)
            next_logp = next_and_ex_logp[:, : rows[0]]
            target_h = torch.cat([encode(next_obs, target=True), encode(ex_obs, target=True)], 1)
            next_q, ex_next_q = self.intentions.q(target_h, next_and_ex_act, target=True).min(0).values.split(rows, -1)
            if a.reward_model == "rce":
                target, weight = rce_targets(torch.sigmoid(next_q), a.gamma)
            else:
                target = buffer_reward + bootstrap_discount * (next_q - alpha * next_logp)
            ex_reward = self.reward.example_reward(ex_obs) if rows[1] else ex_next_q.new_zeros(T, 0)
            ex_target = a.reward_scale * ex_reward + a.gamma * ex_next_q

        q, q_ex = self.intentions.q(h, torch.cat([act.expand(T, *act.shape), ex_act], 1)).split(rows, -1)
        # As the reference: every term is summed over rows and divided by the batch's rows, replay and
        # all tasks' examples, so a task's examples weigh by their share of the batch.
        total_rows = rows[0] + (0 if examples is None else float(examples.weight.sum()))
        if a.reward_model == "rce":
            critic_loss = rce_loss(q, q_ex, target, weight, ex_weight, a.gamma)  # (2, T) sums
        else:
            critic_loss = (q - target).square().sum(-1) + (ex_weight * (q_ex - ex_target).square()).sum(-1)
            if a.value_penalty > 0:
                if self.reward.learned:  # minimum of the learned reward over this batch (thesis Alg. 4)
                    min_reward = step_rewards.flatten(1).min(1).values
                    if rows[1]:
                        min_reward = torch.minimum(
                            min_reward, ex_reward.masked_fill(ex_weight == 0, math.inf).min(1).values
                        )
                else:
                    min_reward = torch.full((T,), self.reward.policy_label, device=dev)
                q_ex_min = q_ex.detach().min(0).values
                if a.vp_q_max == "max":
                    example_q = q_ex_min.masked_fill(ex_weight == 0, -math.inf).amax(-1)
                else:
                    example_q = (ex_weight * q_ex_min).sum(-1) / ex_weight.sum(-1)
                q_max, q_min = self.bounds.update(example_q, min_reward, self.reward.learned)
                penalty = value_penalty(q, q_max.unsqueeze(-1), q_min.unsqueeze(-1), a.value_penalty)  # row mean
                critic_loss = critic_loss + rows[0] * penalty
                stats["q_max"], stats["q_min"] = q_max, q_min
        critic_loss = critic_loss / total_rows
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.sum().backward()
        torch.nn.utils.clip_grad_norm_(self.intentions.critic_parameters(), a.max_grad_norm)
        self.critic_opt.step()

        # Policies and temperatures learn from replay rows only, after the critic step (the reference's
        # order: the updated trunk and Q-functions score the policies' actions).
        self.intentions.critic.requires_grad_(False)
        with torch.no_grad():
            h = encode(obs)
        new_act, logp = self.intentions.sample(h)
        q_pi = self.intentions.q(h, new_act)
        value = (torch.sigmoid(q_pi) if a.reward_model == "rce" else q_pi).min(0).values
        actor_loss = (alpha * logp - value).mean(-1)  # (T,)
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.sum().backward()
        torch.nn.utils.clip_grad_norm_(self.intentions.actor_parameters(), a.max_grad_norm)
        self.actor_opt.step()
        self.intentions.critic.requires_grad_(True)

        with torch.no_grad():  # the updated policies' log-probabilities, as the reference's alpha step
            logp = self.intentions.sample(h)[1]
        alpha_loss = -(self.intentions.log_alpha.unsqueeze(-1) * (logp + self.target_entropy)).mean(-1)
        self.alpha_opt.zero_grad(set_to_none=True)
        alpha_loss.sum().backward()
        torch.nn.utils.clip_grad_norm_([self.intentions.log_alpha], a.max_grad_norm)
        self.alpha_opt.step()

        polyak_update(self.intentions.target_pairs(), a.polyak)
        stats |= {
            "critic_loss": critic_loss.detach().mean(0),
            "actor_loss": actor_loss.detach(),
            "alpha": self.intentions.alpha.detach(),
            "q_buffer": q.detach().min(0).values.mean(-1),
        }
        if rows[1]:
            stats["q_examples"] = (ex_weight * q_ex.detach().min(0).values).sum(-1) / ex_weight.sum(-1)
        return stats

    # -- checkpoints --------------------------------------------------------------------------------

    def state_dict(self) -> dict:
        """Intentions, optimizers, value bounds (and a learned reward with its optimizer), for a checkpoint."""
        state = {
            "intentions": self.intentions.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "bounds": self.bounds.state_dict(),
        }
        if self.reward.learned:
            state |= {"reward": self.reward.state_dict(), "reward_opt": self.reward_opt.state_dict()}
        return state

    def load_state_dict(self, state: dict) -> None:
        """Restores what `state_dict` returned."""
        self.intentions.load_state_dict(state["intentions"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        self.bounds.load_state_dict(state["bounds"])
        if self.reward.learned:
            self.reward.load_state_dict(state["reward"])
            self.reward_opt.load_state_dict(state["reward_opt"])


def metrics_row(stats: dict[str, torch.Tensor], tasks: list[str]) -> dict[str, float]:
    """Flatten per-task tensors (num_tasks,) to `name/task` floats for metrics.jsonl."""
    return {f"{name}/{t}": v for name, value in stats.items() for t, v in zip(tasks, value.tolist(), strict=True)}


# ---------------------------------------------------------------------------------------------------
# The training loop


def train(
    args: VPACEArgs,
    env_factory: Callable[[str], gym.Env] | None = None,
    examples: dict[str, TaskExamples] | None = None,
) -> dict[str, float]:
    """Train; returns the last evaluation's metrics (empty if none ran).

    `env_factory(task)` and `examples` (per task) replace the environment lookup and the example datasets,
    e.g. in tests or when examples come from numpy files.
    """
    from shiftkit.policies.run_dir import RunDir, dataset_records, torch_device, versions

    args.validate()
    tasks = args.tasks
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    device = torch_device(args.device)
    run = RunDir(Path(args.output_dir), resume=args.resume)

    # Data and environments.
    sources: list[Dataset] = []
    env_factory = env_factory or (lambda task: make_env(args.env, task, args.env_kwargs))
    env, eval_env = env_factory(args.main_task), env_factory(args.main_task)
    if examples is None:
        names = getattr(env.unwrapped, "observation_names", None)
        examples, sources = load_dataset_examples(
            args.examples,
            tasks,
            with_actions=args.full_trajectories,
            observation_names=list(names) if names is not None else None,
            require_example_set=not (args.full_trajectories or args.frames_as_examples),
        )
    missing = [t for t in tasks if t not in examples]
    if missing:
        raise ConfigError(f"no examples given for task(s) {missing}")
    example_buffer = ExampleBuffer(examples, tasks, args.aug_factor, args.examples_per_task)
    if not isinstance(env.action_space, gym.spaces.Box):
        raise ConfigError(f"environment {args.env!r} needs a continuous (Box) action space")
    obs_dim = flat_obs(env.observation_space.sample()).shape[0]
    if obs_dim != example_buffer.obs_dim:
        raise ConfigError(f"examples have {example_buffer.obs_dim}-dim states but {args.env!r} observes {obs_dim}")
    horizon = (
        args.episode_steps
        or (env.spec.max_episode_steps if env.spec else None)
        or getattr(env.unwrapped, "max_episode_steps", None)
    )  # shiftkit envs built by make() carry their own limit
    if not horizon:
        raise ConfigError(f"environment {args.env!r} has no time limit; set --episode-steps")
    period = math.ceil(horizon / args.num_periods)

    # Learner, buffer, scheduler, random generators.
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    if device.type == "cpu":
        keep_freed_memory()  # each update frees and reallocates megabyte tensors (process-wide setting)
    agent = Agent(args, obs_dim, env.action_space, device)
    act_dim = int(np.prod(env.action_space.shape))
    replay = ReplayBuffer(args.total_steps, obs_dim, act_dim)
    if args.scheduler == "learned":
        scheduler = QTableScheduler(
            tasks, args.num_periods, args.gamma, handcraft_rate=args.handcraft_rate, handcrafted=args.handcrafted
        )
    else:
        scheduler = WeightedRandomScheduler(
            tasks, args.num_periods, args.main_rate, args.handcraft_rate, args.handcrafted
        )
    step, episode, last_eval, best_eval = 0, 0, {}, {}
    state = run.load_latest() if args.resume else None
    if state is not None:
        agent.load_state_dict(state["agent"])
        replay.load_state_dict(state["replay"])
        scheduler.load_state_dict(state["scheduler"])
        rng.bit_generator.state = state["numpy_rng"]
        torch.set_rng_state(state["torch_rng"])
        step, episode, last_eval = state["step"], state["episode"], state["last_eval"]
        best_eval = state.get("best_eval", {})
    run.write_config(
        {
            "trainer": "lfgp" if args.full_trajectories else "vpace",
            "env": args.env,
            "args": dataclasses.asdict(args),
            "datasets": dataset_records(sources),
            "seed": args.seed,
            "versions": versions(),
            "examples_per_task": example_buffer.sizes(),
        },
        ignore_on_resume=("resume", "total_steps"),
    )  # a finished run may be continued for longer

    def checkpoint() -> None:
        run.save_checkpoint(
            step,
            {
                "agent": agent.state_dict(),
                "replay": replay.state_dict(),
                "scheduler": scheduler.state_dict(),
                "numpy_rng": rng.bit_generator.state,
                "torch_rng": torch.get_rng_state(),
                "step": step,
                "episode": episode,
                "last_eval": last_eval,
                "best_eval": best_eval,
            },
        )

    next_checkpoint = (step // args.checkpoint_every + 1) * args.checkpoint_every
    stats: dict[str, torch.Tensor] = {}
    while step < args.total_steps:
        obs = flat_obs(env.reset(seed=args.seed * 1_000_000 + episode)[0])
        plan = scheduler.plan_episode(rng)
        start = replay.pointer  # this episode's rows, for a learned scheduler
        for t in range(horizon):
            task = plan[min(t // period, args.num_periods - 1)]
            if step < args.random_steps:
                action = rng.uniform(-1.0, 1.0, act_dim).astype(np.float32)
            else:
                action = agent.act(obs, task)
            next_obs, _, terminated, truncated, _ = env.step(agent.env_action(action))
            next_obs = flat_obs(next_obs)
            step += 1
            episode_over = terminated or truncated or t + 1 == horizon or step == args.total_steps
            replay.add(obs, action, next_obs, episode_over)
            obs = next_obs

            if step >= args.buffer_warmup:
                stats = agent.update(*sample_update(args, step, replay, example_buffer, rng))
            if step % args.log_every == 0 and stats:
                run.log(step, "train", episode=episode, **metrics_row(stats, tasks))
            if args.eval_every and step % args.eval_every == 0:
                last_eval = evaluate(
                    agent, eval_env, args.eval_episodes, horizon, EVAL_SEED_OFFSET + args.seed * 1_000_000
                )
                run.log(step, "eval", **last_eval)
                if improves(last_eval, best_eval):
                    best_eval = {**last_eval, "step": step}
                    run.save_best(step, {"agent": {"intentions": agent.intentions.state_dict()}, "eval": best_eval})
            if episode_over:
                break
        if scheduler.learned:
            rows = (start + np.arange(t + 1)) % replay.capacity
            scheduler.update(plan, agent.main_task_rewards(replay.obs[rows], replay.act[rows]), period)
        episode += 1
        if step >= next_checkpoint or step == args.total_steps:
            checkpoint()
            next_checkpoint = (step // args.checkpoint_every + 1) * args.checkpoint_every

    run.write_model_card(
        {
            "step": step,
            **{f"eval/{k}": v for k, v in last_eval.items()},
            **{f"best_eval/{k}": v for k, v in best_eval.items()},
        }
    )
    env.close()
    eval_env.close()
    return last_eval


class MainIntentionPolicy:
    """A trained agent's main intention acting with its mean action (docs/vpace.md), in the policy
    interface of `shiftkit eval`: one `observation.state` input named like the env's observation."""

    def __init__(
        self, agent: Agent, task: int, observation_names: list[str], action_names: list[str] | None = None
    ) -> None:
        self.agent, self.task, self.action_names = agent, task, action_names
        self.features = {"observation.state": {"shape": (len(observation_names),), "names": list(observation_names)}}

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The env action for one observation: the main intention's mean action, mapped to the env's action bounds."""
        action = self.agent.act(np.asarray(obs["observation.state"], np.float32), self.task, deterministic=True)
        return self.agent.env_action(action)


def load_policy(path: str | Path, device: str = "cpu") -> MainIntentionPolicy:
    """The main intention of a VPACE/LfGP run folder (its newest checkpoint) or of a checkpoint file,
    e.g. `RUN/checkpoints/best.safetensors` for the best evaluated one."""
    from shiftkit.datasets.dataclass_config import from_dict
    from shiftkit.datasets.errors import DatasetError
    from shiftkit.policies.run_dir import RunDir, load_checkpoint, run_folder, torch_device

    path, run = Path(path), RunDir(run_folder(path), resume=True)
    checkpoint = run.latest_checkpoint() if path.is_dir() else path
    config = run.read_config()
    if checkpoint is None or not checkpoint.is_file() or config is None:
        raise DatasetError(f"{path}: no VPACE checkpoint with its run's config.json")
    args = from_dict(VPACEArgs, config["args"], f"{run.path}/config.json")
    env = make_env(args.env, args.main_task, args.env_kwargs)
    names = getattr(env.unwrapped, "observation_names", None)
    if names is None:
        raise ConfigError(f"environment {args.env!r} does not name its observation dimensions")
    agent = Agent(args, flat_obs(env.observation_space.sample()).shape[0], env.action_space, torch_device(device))
    action_names = getattr(env.unwrapped, "action_names", None)
    env.close()
    state = load_checkpoint(checkpoint, device)
    try:
        agent.intentions.load_state_dict(state["agent"]["intentions"])
    except (KeyError, TypeError, RuntimeError) as exc:
        raise DatasetError(f"{checkpoint}: not a checkpoint of this run's agent ({type(exc).__name__})") from None
    return MainIntentionPolicy(
        agent, args.tasks.index(args.main_task), list(names), None if action_names is None else list(action_names)
    )
