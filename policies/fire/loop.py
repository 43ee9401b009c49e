"""FIRE: failure identification to reduce expert burden (thesis ch. 5, Algorithm 2; docs/fire.md).

A BC policy (thesis 5.4.2: one 2x256 MLP with a tanh output), initialised from a dataset, runs
episodes in a registered environment. Warm-up: until `d_start` policy samples exist (10k, 5.4.2) the
policy runs on its own (no prediction, stop, takeover or BC update); then D trains and Algorithm 2
proper begins. At every step a failure predictor (beta rule, GDA, ensemble doubt or GDA-or-doubt)
looks at the discriminator score D(s, a) and the ensemble's doubt; a predicted failure stops the run
and asks the expert "will it fail?". The simulated expert (`oracle.SimulatedOracle`) answers by
forking the simulator: yes (true positive) and it takes over, correcting until the policy can finish
from the current state, then hands control back (several times per episode if needed), its
corrections joining the expert set; no (false positive) and the run goes on. It also stops failures
nobody predicted once they show (false negative). After each episode: a successful episode's final
(s_T, a_T) joins the expert set (not counted as an expert sample), GDA learns from the executed
segments (a policy segment ending in an intervention failed), D trains for as many steps as the
episode had, BC takes as many gradient steps on the expert set (lr 1e-4), and every
`retrain_every` (d = 500) new expert-set frames BC is retrained on it, warm-started, with early
stopping on held-out demonstrations and corrections that the per-episode steps never sample.
Execution time counts the demonstrations, the warm-up and every later step.

Run folder (`run_dir.RunDir` layout, trainer "fire"):
    config.json, metrics.jsonl (one "episode" line per episode, "eval" lines), checkpoints/ (the full
    loop state after every episode: a SIGKILLed run resumes there with `resume=True`),
    bc-init/ (the initial BC run), policy/ (a BC run folder of the current policy, loadable by
    `shiftkit eval`), episodes/episode_XXXXXX.npz (every executed episode's frames and signals),
    rollouts/ (at the end: the executed episodes as lerobot's DAgger strategy records them,
    `dagger_recording`).
The aggregated LeRobot dataset is then made from the demonstrations and rollouts/ by offline FIRE
(`fire.aggregate`), the code `shiftkit fire aggregate` runs on a robot's recordings, with this run's
seed and settings: the same bytes either way.
"""

from __future__ import annotations

import dataclasses
import math
import time
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
from shiftkit.policies.data import FrameTable, open_datasets, refuse_example_sets
from shiftkit.policies.evaluation import ObservationMap, run_episodes, wilson_interval
from shiftkit.policies.fire.aggregate import SOURCE_EXPERT, aggregate
from shiftkit.policies.fire.config import FireArgs, nest_bc_settings
from shiftkit.policies.fire.dagger_recording import rollout_repo_id, write_recording
from shiftkit.policies.fire.discriminator import Discriminator, DiscriminatorConfig
from shiftkit.policies.fire.episode import Agent, EpisodeResult, recordable_features, run_episode
from shiftkit.policies.fire.failure_predictors import BetaRule, GDARule, OrRule, make_predictor
from shiftkit.policies.fire.learning import online_update, retrain
from shiftkit.policies.fire.oracle import SimulatedOracle, scripted_expert
from shiftkit.policies.fire.recording import aggregate_args, recorded_episodes, save_npz
from shiftkit.policies.fire.runs import summary as run_summary
from shiftkit.policies.frame_buffer import FrameBuffer
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
    """Everything the loop learns and counts: the policy and its optimisers, D, the predictor, the GDA
    statistics, the expert and policy sets (and which expert frames the retraining holds out), the
    RNGs and counters. A checkpoint holds its `state_dict`, so a resumed run continues where the
    killed one stopped."""

    policy: BCPolicy
    optimizers: list
    disc: Discriminator
    agent: Agent
    """The policy and D acting (they share the weights above)."""
    predictor: Any
    gda: GDARule
    """The GDA rule learning from executed segments: the predictor's own, or one for the ROC scores."""
    expert_set: FrameBuffer
    held_out: np.ndarray
    """Per expert-set frame: kept for the full retraining's validation, never sampled by the updates."""
    policy_set: FrameBuffer
    rng: np.random.Generator
    oracle: SimulatedOracle
    counters: dict

    def state_dict(self) -> dict[str, Any]:
        """Everything a checkpoint holds to resume the loop exactly."""
        return {
            "policy": self.policy.state_dict(),
            "optimizers": [o.state_dict() for o in self.optimizers],
            "disc": self.disc.state_dict(),
            "predictor": self.predictor.state_dict(),
            "gda": self.gda.state_dict(payloads=True),
            "expert_set": self.expert_set.state_dict(),
            "held_out": self.held_out,
            "policy_set": self.policy_set.state_dict(),
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
        self.gda.load_state_dict(state["gda"])  # after the predictor's: the stored segments win
        self.expert_set.load_state_dict(state["expert_set"])
        self.held_out = np.asarray(state["held_out"], dtype=bool)
        self.policy_set.load_state_dict(state["policy_set"])
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
    scripted_expert(args.env, env, args.expert_policy)  # the env must have that expert, acting from any state
    return env


def _initial_bc(args: FireArgs, bc_dir: Path, device: torch.device) -> BCPolicy:
    """BC initialised from the demonstrations (its own run folder, resumable too), with FIRE's own
    BC settings (`FireArgs.bc`), not `shiftkit train bc`'s defaults."""
    train_bc(
        BCArgs(
            **dataclasses.asdict(args.bc),
            datasets=[args.dataset],
            root=args.root,
            output_dir=str(bc_dir),
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
    """The loop's state before the first episode: the expert set holds the demonstrations, the
    episodes the initial BC held out (the same seeded split) kept apart for the retraining."""
    keys = [*policy.features, "action"]
    demo_frames = FrameTable([ds], keys)
    expert_set, policy_set = FrameBuffer(keys), FrameBuffer(keys)
    expert_set.add(demo_frames.gather(np.arange(demo_frames.num_frames)))
    held_out = np.zeros(demo_frames.num_frames, dtype=bool)
    held_out[demo_frames.split_episodes(args.hold_out_share, args.seed)[1]] = True
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
    if args.doubt_threshold is None and len(policy.members) > 1:
        with torch.no_grad():
            outs = policy.member_outputs(expert_set.gather(np.arange(len(expert_set)), device))
        doubt_threshold = float(ensemble_doubt(outs).max()) or 1e-6
    else:
        doubt_threshold = args.doubt_threshold or 1e-6
    predictor = make_predictor(args.predictor, doubt_threshold, beta=args.beta, gamma=args.gamma)
    own = [r for r in (predictor, getattr(predictor, "a", None)) if isinstance(r, GDARule)]
    gda = own[0] if own else GDARule(args.gamma)
    margin = args.expert_margin if args.expert_margin is not None else int(np.median(demo_lengths))
    fps = getattr(env, "control_hz", None) or ds.meta.fps
    oracle = SimulatedOracle(
        args.env,
        agent,
        check_step=max(0, env.max_episode_steps - margin),
        expert=args.expert_policy,
        stall_steps=max(2, math.ceil(args.stall_seconds * fps)),
        stall_tolerance=args.stall_tolerance,
    )
    rng = np.random.default_rng([args.seed, 0xF12E])
    torch.manual_seed(args.seed)  # the global generator is checkpointed: its bytes follow the seed
    counters = {
        "episode": 0,
        "corrections": 0,
        "interventions": 0,
        "hand_backs": 0,
        "demo_frames": demo_frames.num_frames,
        "env_steps": 0,
        "since_retrain": 0,
        "wall_time": 0.0,
        "retrains": 0,
        "d_ready_episode": None,
    }
    return Learner(
        policy, optimizers, disc, agent, predictor, gda, expert_set, held_out, policy_set, rng, oracle, counters
    )


def _learn(learner: Learner, ep: EpisodeResult, args: FireArgs, active: bool, device: torch.device) -> dict:
    """Algorithm 2, lines 25-40, after one episode; returns the episode's learning metrics. Until D is
    ready (`active` False) the policy's frames only gather (D_pi, the GDA segments) and BC stays as
    the demonstrations made it."""
    n = len(ep.frames["action"])
    by_expert = ep.frames["source"][:, 0] == SOURCE_EXPERT
    keep = {k: ep.frames[k] for k in learner.expert_set.keys}
    # each correction joins D_E, a seeded share of the corrections held out for the retraining
    held = [learner.rng.random() < args.hold_out_share for s in ep.segments if s.expert]
    stretch_held = np.zeros(n, dtype=bool)
    for segment, h in zip((s for s in ep.segments if s.expert), held, strict=True):
        stretch_held[slice(*segment.payload)] = h
    learner.expert_set.add({k: v[by_expert] for k, v in keep.items()})
    learner.held_out = np.r_[learner.held_out, stretch_held[by_expert]]
    learner.policy_set.add({k: v[~by_expert] for k, v in keep.items()})
    added = int(by_expert.sum())
    if ep.success and not by_expert[-1]:  # the final (s_T, a_T) of a success is expert data (5.3.4),
        learner.expert_set.add({k: v[-1:] for k, v in keep.items()})  # not an expert sample
        learner.held_out = np.r_[learner.held_out, False]
        added += 1
    counters = learner.counters
    counters["corrections"] += int(by_expert.sum())
    counters["interventions"] += len(ep.interventions)
    counters["hand_backs"] += sum(x["end"] < n for x in ep.interventions)
    counters["since_retrain"] += added
    counters["env_steps"] += n

    # scores for ROC curves, from statistics of earlier episodes only (doubt: with an ensemble)
    scores = {"beta": BetaRule().score(ep.trace), "gda": learner.gda.score(ep.trace)}
    if len(learner.policy.members) > 1:
        scores["doubt"] = float(np.max(ep.trace.doubt)) if len(ep.trace.doubt) else 0.0
    # GDA learns from the executed segments, D from both sets once enough policy samples exist
    disc, gda = learner.disc, learner.gda
    for segment in ep.segments:
        segment.payload = {k: v[slice(*segment.payload)] for k, v in keep.items()}
        if disc.updates:
            segment.d = disc.score(segment.payload)
        gda.add_segment(segment)
    gda.add_outcome(ep.policy_failed)
    d_metrics = {}
    if disc.ready(len(learner.policy_set)):
        d_metrics = disc.update(learner.expert_set, learner.policy_set, n, learner.rng)
        gda.rescore(disc.score)
        if counters["d_ready_episode"] is None:
            counters["d_ready_episode"] = counters["episode"]
    bc_loss, retrained = None, {}
    if active:
        train_rows = np.flatnonzero(~learner.held_out)
        bc_loss = online_update(
            learner.policy, learner.optimizers, learner.expert_set, train_rows, n, args, learner.rng, device
        )
        if counters["since_retrain"] >= args.retrain_every:
            seed = args.seed + counters["retrains"]
            retrained = retrain(
                learner.policy, learner.optimizers, learner.expert_set, learner.held_out, args, seed, device
            )
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
        "expert_samples": counters["demo_frames"] + counters["corrections"],
        "corrections": counters["corrections"],
        "execution_time_s": (counters["demo_frames"] + counters["env_steps"]) / fps,
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
        stored_args=nest_bc_settings,
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
        stored_args=nest_bc_settings,
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
        active = learner.disc.updates > 0  # D trained: Algorithm 2 proper (before: the warm-up)
        ep = run_episode(env, args.env_seed + i, agent, learner.predictor, oracle, active, observed, args.fp_cooldown)
        exec_time = time.perf_counter() - started
        exec_cpu = time.process_time() - started_cpu  # unlike wall time, not stretched by other processes
        learned = _learn(learner, ep, args, active, device)
        bar.update(min(learned["episode_expert_samples"], budget - bar.n))
        counters["wall_time"] += time.perf_counter() - started
        counters["episode"] += 1

        first = ep.interventions[0]["start"] if ep.interventions else None
        meta = {
            "outcome": "success" if ep.success else "failure",
            "seed": args.env_seed + i,
            "fire": {
                "episode": i,
                "policy_outcome": "failure" if ep.policy_failed else "success",
                "feedback": ep.feedback,
                "intervened_at": first,
                "interventions": ep.interventions,
                "predictor": args.predictor,
            },
        }
        save_npz(episodes_dir / f"episode_{i:06d}.npz", ep.frames, meta)
        metrics = {
            "episode": i,
            "seed": args.env_seed + i,
            "success": ep.success,
            "policy_success": not ep.policy_failed,
            "d_ready": active,
            "predictions": ep.predictions,
            "feedback": ep.feedback,
            "intervened_at": first,
            "interventions": ep.interventions,
            "stops": ep.stops,
            "length": len(ep.frames["action"]),
            "episode_expert_samples": learned.pop("episode_expert_samples"),
            "corrections": counters["corrections"],
            "expert_samples": counters["demo_frames"] + counters["corrections"],
            "policy_samples": len(learner.policy_set),
            "env_steps": counters["env_steps"],
            "execution_time_s": (counters["demo_frames"] + counters["env_steps"]) / fps,
            "wall_time_s": counters["wall_time"],
            "episode_exec_s": exec_time,
            "episode_cpu_s": exec_cpu,
            "look_ahead_steps": oracle.look_ahead_steps,
            "forks": oracle.forks,
            "deadline_step": oracle.check_step,
        }
        run_dir.log(counters["episode"], "episode", **metrics, **learned)
        if args.eval_every and counters["episode"] % args.eval_every == 0:
            run_dir.log(counters["episode"], "eval", **_evaluate(learner, env, args, fps))
        checkpoint()

    bar.close()
    # --- the rollouts as lerobot's DAgger strategy records them, then offline FIRE over them: the
    # aggregated dataset, predictor file and ROC come from the same code a lab runs on its recordings
    summary = run_summary(run_dir, counters)
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
                sources=[
                    {
                        "kind": "simulator",
                        "env": args.env,
                        "task": args.task,
                        "fire_run": str(run_dir.path),
                        "episodes": counters["episode"],
                        "env_seed": args.env_seed,
                    }
                ],
            )
        aggregate(aggregate_args(args, [str(rollouts)], str(bc_dir), dataset_root))
    summary["dataset"] = str(dataset_root)
    checkpoint(summary)
    # The policy folder is a finished BC run: `shiftkit eval` takes it as final, and it has a card.
    policy_run.write_model_card({k: v for k, v in summary.items() if isinstance(v, int | float | str)})
    env.close()
    return summary
