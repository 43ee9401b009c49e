"""FIRE: failure identification to reduce expert burden (thesis ch. 5, Algorithm 2; docs/fire.md).

A BC policy, initialised from a dataset, runs episodes in a registered environment. At every step a
failure predictor (beta rule, GDA, ensemble doubt or GDA-or-doubt) looks at the discriminator score
D(s, a) and the ensemble's doubt; a predicted failure stops the run and asks the expert "will it
fail?". The simulated expert (`oracle.SimulatedOracle`) answers by forking the simulator: yes (true
positive) and it takes over until the episode ends, its corrections joining the expert set; no (false
positive) and the run goes on. It also stops failures nobody predicted (false negative). After each
episode: a successful episode's final (s_T, a_T) joins the expert set, D trains for as many steps as
the episode had, BC takes as many gradient steps on the expert set (lr 1e-4), the predictors update
their statistics, and every `retrain_every` (d = 500) new expert samples BC is retrained on the whole
expert set, warm-started, with early stopping on a hold-out.

Run folder (`run_dir.RunDir` layout, trainer "fire"):
    config.json, metrics.jsonl (one "episode" line per episode, "eval" lines), checkpoints/ (the full
    loop state after every episode: a SIGKILLed run resumes there with `resume=True`),
    bc-init/ (the initial BC run), policy/ (a BC run folder of the current policy, loadable by
    `shiftkit eval`), episodes/episode_XXXXXX.npz (every executed episode's frames and signals),
    rollouts/ (at the end: the executed episodes as lerobot's DAgger strategy records them,
    `dagger_recording`).
The aggregated LeRobot dataset is then made from the demonstrations and rollouts/ by offline FIRE
(`fire_aggregate`), the code `shiftkit fire aggregate` runs on a robot's recordings, with this run's
seed and settings: the same bytes either way.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.features import user_features
from shiftkit.datasets.ids import lerobot_home
from shiftkit.datasets.provenance import recorded_envs
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.policies.bc_policy import BCPolicy, ensemble_doubt, load_policy
from shiftkit.policies.dagger_recording import rollout_repo_id, write_recording
from shiftkit.policies.data import FrameTable, open_datasets, refuse_example_sets
from shiftkit.policies.discriminator import Discriminator, DiscriminatorConfig
from shiftkit.policies.evaluation import ObservationMap, run_episodes, wilson_interval
from shiftkit.policies.failure_predictors import BetaRule, GDARule, OrRule, make_predictor
from shiftkit.policies.fire_aggregate import SOURCE_EXPERT, aggregate
from shiftkit.policies.fire_config import FireArgs
from shiftkit.policies.fire_episode import Agent, EpisodeResult, recordable_features, run_episode
from shiftkit.policies.fire_learning import online_update, retrain
from shiftkit.policies.fire_recording import aggregate_args, recorded_episodes, save_npz
from shiftkit.policies.fire_runs import summary as run_summary
from shiftkit.policies.frame_buffer import FrameBuffer
from shiftkit.policies.oracle import SimulatedOracle, scripted_expert
from shiftkit.policies.run_dir import RunDir, dataset_records, torch_device, versions
from shiftkit.policies.trainers.bc.args import BCArgs
from shiftkit.policies.trainers.bc.training import train as train_bc

EVAL_SEED = 100_000


def thresholds(predictor: Any) -> dict[str, float]:
    """The current threshold(s) of a predictor, for the metrics."""
    if isinstance(predictor, OrRule):
        return {**thresholds(predictor.a), **thresholds(predictor.b)}
    if isinstance(predictor, BetaRule):
        return {"beta": predictor.beta}
    if isinstance(predictor, GDARule):
        return {"gamma": predictor.gamma, **({"beta": predictor.beta.beta} if predictor.beta else {})}
    return {"doubt_threshold": predictor.threshold}


@dataclass
class Learner:
    """Everything the loop learns and counts: the policy and its optimisers, D, the predictors, the
    expert and policy sets, the trajectories behind the GDA statistics, the RNGs and counters. A
    checkpoint holds its `state_dict`, so a resumed run continues where the killed one stopped."""

    policy: BCPolicy
    optimizers: list
    disc: Discriminator
    agent: Agent
    """The policy and D acting (they share the weights above)."""
    predictor: Any
    roc_gda: GDARule
    """GDA statistics for the ROC scores, whichever predictor runs."""
    expert_set: FrameBuffer
    policy_set: FrameBuffer
    history: dict[bool, deque]
    """The policy trajectories behind the GDA statistics (window per outcome), re-scored whenever D
    changes."""
    rng: np.random.Generator
    oracle: SimulatedOracle
    counters: dict

    def gda_rules(self) -> list[GDARule]:
        """The GDA rules whose statistics follow D: the ROC one and the predictor's own."""
        own = (self.predictor, getattr(self.predictor, "a", None))
        return [self.roc_gda, *(r for r in own if isinstance(r, GDARule))]

    def state_dict(self) -> dict[str, Any]:
        """Everything a checkpoint holds to resume the loop exactly."""
        return {
            "policy": self.policy.state_dict(),
            "optimizers": [o.state_dict() for o in self.optimizers],
            "disc": self.disc.state_dict(),
            "predictor": self.predictor.state_dict(),
            "roc_gda": self.roc_gda.state_dict(),
            "expert_set": self.expert_set.state_dict(),
            "policy_set": self.policy_set.state_dict(),
            "history": {failed: list(h) for failed, h in self.history.items()},
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "counters": self.counters,
            "oracle": (self.oracle.forks, self.oracle.look_ahead_steps),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restores what `state_dict` saved (the RNGs included)."""
        self.policy.load_state_dict(state["policy"])
        for opt, s in zip(self.optimizers, state["optimizers"], strict=True):
            opt.load_state_dict(s)
        self.disc.load_state_dict(state["disc"])
        self.predictor.load_state_dict(state["predictor"])
        self.roc_gda.load_state_dict(state["roc_gda"])
        self.expert_set.load_state_dict(state["expert_set"])
        self.policy_set.load_state_dict(state["policy_set"])
        for failed, trajectories in state["history"].items():
            self.history[failed].extend(trajectories)
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.counters = state["counters"]
        self.oracle.forks, self.oracle.look_ahead_steps = state["oracle"]


def _open_env(args: FireArgs, fps: int, dataset: Path, name: str) -> Any:
    """The run's environment at the rate (`fps`) of the dataset `name` at `dataset`; ConfigError for
    one FIRE cannot run in."""
    from shiftkit.envs import ENV_TASKS, env_family, make

    try:
        family = env_family(args.env)
        env_kwargs = dict(args.env_kwargs)
        if "control_hz" not in env_kwargs and fps in family.control_rates:
            env_kwargs["control_hz"] = fps
        env = make(args.env, args.task, **env_kwargs)
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(exc)) from None
    # Another registered env's dataset: its rate and observations are not this env's.
    recorded = sorted(recorded_envs(dataset) & set(ENV_TASKS))
    if recorded and args.env not in recorded:
        env.close()
        raise ConfigError(
            f"{name} was recorded in {', '.join(recorded)}, not {args.env}: "
            f"FIRE it in the env it was recorded in (--env {recorded[0]})"
        )
    if round(getattr(env, "control_hz", fps)) != fps:
        env.close()
        offered = ", ".join(str(r) for r in sorted(family.control_rates))
        raise ConfigError(
            f"the dataset is at {fps} fps but {args.env} would run at {env.control_hz} Hz ({args.env} offers "
            f"{offered} Hz): FIRE a dataset recorded at a rate the env offers"
        )
    scripted_expert(args.env, env)  # the env must have an expert that acts from any state
    return env


def _initial_bc(args: FireArgs, bc_dir: Path, device: torch.device) -> BCPolicy:
    """BC initialised from the demonstrations (its own run folder, resumable too)."""
    train_bc(
        BCArgs(
            datasets=[args.dataset],
            root=args.root,
            output_dir=str(bc_dir),
            regime=args.bc_regime,
            steps=args.bc_steps,
            ensemble_size=args.ensemble_size,
            hidden=args.hidden,
            batch_size=args.batch_size,
            seed=args.seed,
            device=args.device,
            threads=args.threads,
            resume=(bc_dir / "config.json").exists(),
            log_every=10**9,
        )
    )
    return load_policy(bc_dir, device=str(device))


def _learner(
    args: FireArgs, policy: BCPolicy, ds: Any, env: Any, obs_map: ObservationMap, device: torch.device
) -> Learner:
    """The loop's state before the first episode: the expert set holds the demonstrations."""
    keys = [*policy.features, "action"]
    demo_frames = FrameTable([ds], keys)
    expert_set, policy_set = FrameBuffer(keys), FrameBuffer(keys)
    expert_set.add(demo_frames.gather(np.arange(demo_frames.num_frames)))
    demo_lengths = [end - start for start, end in demo_frames.episodes]
    optimizers = [torch.optim.Adam(net.parameters(), lr=args.online_lr) for net in policy.members]
    disc = Discriminator(
        policy.spec,
        DiscriminatorConfig(
            hidden=args.d_hidden, lr=args.d_lr, grad_penalty=args.grad_penalty, start_after=args.d_start
        ),
        device,
        seed=args.seed,
    )
    agent = Agent(policy, disc, obs_map, device)
    if args.doubt_threshold is None:
        with torch.no_grad():
            outs = policy.member_outputs(expert_set.gather(np.arange(len(expert_set)), device))
        doubt_threshold = float(ensemble_doubt(outs).max()) or 1e-6
    else:
        doubt_threshold = args.doubt_threshold
    predictor = make_predictor(args.predictor, doubt_threshold, beta=args.beta, gamma=args.gamma)
    roc_gda = GDARule(args.gamma)
    history: dict[bool, deque] = {True: deque(maxlen=roc_gda.window), False: deque(maxlen=roc_gda.window)}
    margin = args.expert_margin if args.expert_margin is not None else math.ceil(1.5 * max(demo_lengths))
    oracle = SimulatedOracle(args.env, agent, check_step=max(0, env.max_episode_steps - margin))
    rng = np.random.default_rng([args.seed, 0xF12E])
    counters = {"episode": 0, "corrections": 0, "env_steps": 0, "since_retrain": 0, "wall_time": 0.0, "retrains": 0}
    return Learner(
        policy, optimizers, disc, agent, predictor, roc_gda, expert_set, policy_set, history, rng, oracle, counters
    )


def _learn(learner: Learner, ep: EpisodeResult, args: FireArgs, device: torch.device) -> dict:
    """Algorithm 2, lines 35-40, after one episode; returns the episode's learning metrics."""
    n = len(ep.frames["action"])
    by_expert = ep.frames["source"][:, 0] == SOURCE_EXPERT
    keep = {k: ep.frames[k] for k in learner.expert_set.keys}
    learner.expert_set.add({k: v[by_expert] for k, v in keep.items()})
    learner.policy_set.add({k: v[~by_expert] for k, v in keep.items()})
    added = int(by_expert.sum())
    if ep.success and not by_expert[-1]:  # the final (s_T, a_T) of a success is expert data
        learner.expert_set.add({k: v[-1:] for k, v in keep.items()})
        added += 1
    counters = learner.counters
    counters["corrections"] += int(by_expert.sum())
    counters["since_retrain"] += added
    counters["env_steps"] += n

    # scores for ROC curves, from statistics of earlier episodes only
    scores = {
        "beta": BetaRule().score(ep.trace),
        "gda": learner.roc_gda.score(ep.trace),
        "doubt": float(np.max(ep.trace.doubt)) if len(ep.trace.doubt) else 0.0,
    }
    learner.predictor.update(ep.trace, ep.policy_failed)
    learner.roc_gda.update(ep.trace, ep.policy_failed)
    learner.history[ep.policy_failed].append(ep.trajectory)
    disc = learner.disc
    d_metrics = {}
    if disc.ready(len(learner.policy_set)):
        d_metrics = disc.update(learner.expert_set, learner.policy_set, n, learner.rng)
        rescored = {failed: [disc.score(x) for x in h] for failed, h in learner.history.items()}
        for rule in learner.gda_rules():
            rule.refit(rescored[True], rescored[False])
    bc_loss = online_update(learner.policy, learner.optimizers, learner.expert_set, n, args, learner.rng, device)
    retrained = {}
    if counters["since_retrain"] >= args.retrain_every:
        seed = args.seed + counters["retrains"]
        retrained = retrain(learner.policy, learner.optimizers, learner.expert_set, args, seed, device)
        counters["since_retrain"] -= args.retrain_every
        counters["retrains"] += 1
    return {
        "episode_expert_samples": int(by_expert.sum()),
        "scores": scores,
        "thresholds": thresholds(learner.predictor),
        "bc_loss": bc_loss,
        **d_metrics,
        **retrained,
    }


def _evaluate(learner: Learner, env: Any, args: FireArgs, fps: int) -> dict:
    """The current policy's success over `eval_episodes` fresh seeds."""
    results = run_episodes(learner.policy, env, args.eval_episodes, EVAL_SEED)
    wins = sum(r.success for r in results)
    counters = learner.counters
    return {
        "success_rate": wins / len(results),
        "ci95": list(wilson_interval(wins, len(results))),
        "episodes": len(results),
        "expert_samples": len(learner.expert_set),
        "corrections": counters["corrections"],
        "execution_time_s": counters["env_steps"] / fps,
        "wall_time_s": counters["wall_time"],
    }


def run(args: FireArgs) -> dict:
    """Run (or resume) FIRE and write the aggregated dataset; returns the final summary."""
    args = args.resolved()
    run_dir = RunDir(args.output_dir, args.resume)
    device = torch_device(args.device)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    dataset_root = Path(args.dataset_root) if args.dataset_root else lerobot_home() / args.repo_id

    # --- data and environment, checked before anything is written
    ((resolved, ds),) = opened = open_datasets([args.dataset], args.root)
    refuse_example_sets(opened, "FIRE")
    fps, features = int(ds.meta.fps), user_features(ds.meta.features)
    env = _open_env(args, fps, Path(ds.root), resolved.repo_id)
    observed = recordable_features(features, list(env.observation_names))
    if dataset_root.exists() and not args.resume:
        raise ConfigError(f"aggregated dataset destination already exists: {dataset_root}")
    run_dir.write_config(
        {
            "trainer": "fire",
            "args": dataclasses.asdict(args),
            "datasets": dataset_records([resolved]),
            "env": f"{args.env} / {args.task}",
            "seed": args.seed,
            "versions": versions(),
        },
        ignore_on_resume=("resume", "progress"),
    )
    state = run_dir.load_latest() if args.resume else None
    if state is not None and state["final"]:
        return state["summary"]

    bc_dir = run_dir.path / "bc-init"
    policy = _initial_bc(args, bc_dir, device)
    learner = _learner(args, policy, ds, env, ObservationMap(observed, list(env.observation_names)), device)
    agent, oracle, counters = learner.agent, learner.oracle, learner.counters
    episodes_dir = run_dir.path / "episodes"
    episodes_dir.mkdir(exist_ok=True)
    policy_run = RunDir(run_dir.path / "policy", resume=True)
    policy_run.write_config(
        {
            "trainer": "bc",
            "args": {"fire_run": str(run_dir.path), **dataclasses.asdict(args)},
            "datasets": dataset_records([resolved]),
            "versions": versions(),
        },
        ignore_on_resume=("resume", "progress"),
    )
    if state is not None:
        learner.load_state_dict(state)
        counters = learner.counters
    policy.eval()

    def checkpoint(summary: dict | None = None) -> None:
        step, final = learner.counters["episode"], summary is not None
        model = {"policy_spec": dataclasses.asdict(policy.spec), "model": policy.state_dict()}
        policy_run.save_checkpoint(step, {"trainer": "bc", "final": final, "metrics": None, **model})
        run_dir.save_checkpoint(step, {"trainer": "fire", "final": final, "summary": summary, **learner.state_dict()})

    # --- Algorithm 2: episodes until the expert's budget is spent
    from tqdm import tqdm

    budget = args.budget_expert_samples
    bar = tqdm(total=budget, initial=min(counters["corrections"], budget), unit="correction", disable=not args.progress)
    while counters["corrections"] < budget and (args.max_episodes is None or counters["episode"] < args.max_episodes):
        i, started, started_cpu = counters["episode"], time.perf_counter(), time.process_time()
        d_ready = learner.disc.ready(len(learner.policy_set))
        ep = run_episode(env, args.env_seed + i, agent, learner.predictor, oracle, d_ready, observed, args.fp_cooldown)
        exec_time = time.perf_counter() - started
        exec_cpu = time.process_time() - started_cpu  # unlike wall time, not stretched by other processes
        learned = _learn(learner, ep, args, device)
        bar.update(min(learned["episode_expert_samples"], budget - bar.n))
        counters["wall_time"] += time.perf_counter() - started
        counters["episode"] += 1

        meta = {
            "outcome": "success" if ep.success else "failure",
            "seed": args.env_seed + i,
            "fire": {
                "episode": i,
                "policy_outcome": "failure" if ep.policy_failed else "success",
                "feedback": ep.feedback,
                "intervened_at": ep.intervened_at,
                "predictor": args.predictor,
            },
        }
        save_npz(episodes_dir / f"episode_{i:06d}.npz", ep.frames, meta)
        metrics = {
            "episode": i,
            "seed": args.env_seed + i,
            "success": ep.success,
            "policy_success": not ep.policy_failed,
            "predictions": ep.predictions,
            "feedback": ep.feedback,
            "intervened_at": ep.intervened_at,
            "length": len(ep.frames["action"]),
            "episode_expert_samples": learned.pop("episode_expert_samples"),
            "corrections": counters["corrections"],
            "expert_samples": len(learner.expert_set),
            "env_steps": counters["env_steps"],
            "execution_time_s": counters["env_steps"] / fps,
            "wall_time_s": counters["wall_time"],
            "episode_exec_s": exec_time,
            "episode_cpu_s": exec_cpu,
            "look_ahead_steps": oracle.look_ahead_steps,
            "forks": oracle.forks,
            "d_ready": d_ready,
        }
        run_dir.log(counters["episode"], "episode", **metrics, **learned)
        if args.eval_every and counters["episode"] % args.eval_every == 0:
            run_dir.log(counters["episode"], "eval", **_evaluate(learner, env, args, fps))
        checkpoint()

    bar.close()
    # --- the rollouts as lerobot's DAgger strategy records them, then offline FIRE over them: the
    # aggregated dataset, predictor file and ROC come from the same code a lab runs on its recordings
    summary = run_summary(run_dir, counters, len(learner.expert_set))
    rollouts = run_dir.path / "rollouts"
    if not dataset_root.exists():
        task = next(iter(open_lerobot_dataset(resolved.root).tasks), args.task)
        if not rollouts.exists():  # written atomically from the finished episodes: never partial
            write_recording(
                rollouts,
                rollout_repo_id(run_dir.path.name),
                fps,
                {**observed, "action": features["action"]},
                recorded_episodes(episodes_dir, fps, task),
                robot_type=ds.meta.robot_type,
            )
        aggregate(aggregate_args(args, [str(rollouts)], str(bc_dir), dataset_root))
    summary["dataset"] = str(dataset_root)
    checkpoint(summary)
    # The policy folder is a finished BC run: `shiftkit eval` takes it as final, and it has a card.
    policy_run.write_model_card({k: v for k, v in summary.items() if isinstance(v, int | float | str)})
    env.close()
    return summary
