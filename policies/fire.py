"""FIRE: failure identification to reduce expert burden (thesis ch. 5, Algorithm 2; SPEC 5.4).

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
import io
import json
import math
import os
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ConfigError
from shiftkit.pipelines.features import user_features
from shiftkit.pipelines.lerobot_io import lerobot_home, open_lerobot_dataset
from shiftkit.pipelines.provenance import recorded_envs
from shiftkit.policies.bc import BCArgs, BCPolicy, ensemble_doubt, load_policy, update_members
from shiftkit.policies.bc import train as train_bc
from shiftkit.policies.dagger_recording import rollout_repo_id, write_recording
from shiftkit.policies.data import FrameTable, epoch_batches, open_datasets, refuse_example_sets
from shiftkit.policies.discriminator import Discriminator, DiscriminatorConfig
from shiftkit.policies.evaluation import ObservationMap, run_episodes, wilson_interval
from shiftkit.policies.failure_predictors import (
    PREDICTORS,
    BetaRule,
    EpisodeTrace,
    GDARule,
    OrRule,
    make_predictor,
)
from shiftkit.policies.fire_aggregate import SOURCE_EXPERT, SOURCE_POLICY, AggregateArgs, aggregate
from shiftkit.policies.fire_predictor import RULES
from shiftkit.policies.frame_buffer import FrameBuffer
from shiftkit.policies.oracle import SimulatedOracle, scripted_expert
from shiftkit.policies.run_dir import RunDir, dataset_records, torch_device, versions

EVAL_SEED = 100_000


@dataclass
class FireArgs:
    """Arguments of `shiftkit fire` (defaults: thesis 5.4.2)."""

    dataset: str
    """Dataset ID or local folder of the initial demonstrations."""
    env: str
    """Registered environment (`shiftkit.envs`) with a scripted expert."""
    task: str
    """Task of the environment."""
    output_dir: str
    """Run folder (config, metrics, checkpoints, policy, episodes)."""
    root: str | None = None
    """Local folder of the dataset (else resolved by ID)."""
    predictor: str = "gda"
    """Failure predictor: beta, gda, doubt or gda+doubt."""
    budget_expert_samples: int = 2000
    """Stop once the expert's corrections hold this many samples."""
    max_episodes: int | None = None
    """Stop after this many episodes at the latest."""
    repo_id: str | None = None
    """Repo ID of the aggregated dataset (default: local/<output folder name>)."""
    dataset_root: str | None = None
    """Where the aggregated dataset is written (default: $HF_LEROBOT_HOME/<repo_id>)."""
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    """Environment constructor arguments (control_hz defaults to the dataset's fps)."""
    seed: int = 0
    """Seed of BC, D, sampling and the hold-outs."""
    env_seed: int = 10_000
    """Episode i resets the environment with env_seed + i."""
    # --- BC
    bc_regime: str = "early-stop"
    """Initial BC regime (`shiftkit train bc --regime`)."""
    bc_steps: int | None = None
    """Initial BC steps (fixed regime; a bound for early-stop)."""
    ensemble_size: int = 5
    """BC ensemble members (their spread is the doubt)."""
    hidden: list[int] = field(default_factory=lambda: [256, 256])
    """BC hidden widths."""
    batch_size: int = 64
    """BC batch per member (initial training, updates, retraining)."""
    online_lr: float = 1e-4
    """Learning rate of the per-episode BC updates."""
    retrain_every: int = 500
    """d: full warm-started BC retraining every this many new expert samples."""
    retrain_lr: float = 1e-3
    """Learning rate of the full retraining."""
    retrain_max_epochs: int = 100
    """Most epochs of a full retraining."""
    retrain_patience: int = 10
    """Epochs without hold-out improvement before a retraining member stops."""
    # --- discriminator and predictors
    d_start: int = 10_000
    """Policy samples before D trains and D-based predictions begin."""
    d_lr: float = 1e-3
    """Discriminator learning rate."""
    d_hidden: list[int] = field(default_factory=lambda: [256, 256])
    """Discriminator tanh MLP widths."""
    grad_penalty: float = 10.0
    """Discriminator gradient-penalty weight."""
    beta: int = 20
    """Initial beta of the beta rule."""
    gamma: float = 0.5
    """Initial posterior threshold of the GDA rule."""
    doubt_threshold: float | None = None
    """Initial doubt threshold (default: the largest doubt over the demonstrations' frames)."""
    fp_cooldown: int = 5
    """Steps without predictions after a false positive."""
    expert_margin: int | None = None
    """Steps the expert needs to finish from anywhere: the oracle stops unpredicted failures this many
    steps before the episode's end (default: 1.5x the longest demonstration)."""
    # --- evaluation and bookkeeping
    eval_every: int = 0
    """Evaluate the policy every this many episodes (0: never), on seeds from 100000."""
    eval_episodes: int = 10
    """Episodes per evaluation."""
    device: str = "auto"
    """auto, cpu or cuda."""
    threads: int | None = None
    """CPU threads for torch."""
    resume: bool = False
    """Continue the run in output_dir after its last finished episode."""
    progress: bool = False
    """Show a progress bar over the expert budget."""

    def resolved(self) -> FireArgs:
        """A checked copy; raises ConfigError on bad values."""
        if self.predictor not in PREDICTORS:
            raise ConfigError(f"unknown predictor {self.predictor!r} (choose from {', '.join(PREDICTORS)})")
        positive = {
            "budget_expert_samples": self.budget_expert_samples,
            "ensemble_size": self.ensemble_size,
            "batch_size": self.batch_size,
            "retrain_every": self.retrain_every,
            "retrain_max_epochs": self.retrain_max_epochs,
            "retrain_patience": self.retrain_patience,
            "beta": self.beta,
            "eval_episodes": self.eval_episodes,
            "online_lr": self.online_lr,
            "retrain_lr": self.retrain_lr,
            "d_lr": self.d_lr,
        }
        for name, value in positive.items():
            if not value > 0:
                raise ConfigError(f"{name} must be positive, got {value}")
        for name in ("d_start", "fp_cooldown", "eval_every", "grad_penalty"):
            if getattr(self, name) < 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.max_episodes is not None and self.max_episodes <= 0:
            raise ConfigError(f"max_episodes must be positive, got {self.max_episodes}")
        if not 0.0 < self.gamma < 1.0:
            raise ConfigError(f"gamma must be in (0, 1), got {self.gamma}")
        if self.doubt_threshold is not None and not self.doubt_threshold > 0:
            raise ConfigError(f"doubt_threshold must be positive, got {self.doubt_threshold}")
        if self.expert_margin is not None and self.expert_margin < 0:
            raise ConfigError(f"expert_margin must be >= 0, got {self.expert_margin}")
        if any(h <= 0 for h in [*self.hidden, *self.d_hidden]):
            raise ConfigError("hidden widths must be positive")
        repo_id = self.repo_id or f"local/{Path(self.output_dir).name}"
        if repo_id.count("/") != 1 or not all(repo_id.split("/")):
            raise ConfigError(f"repo_id must look like ORG/NAME, got {repo_id!r}")
        return dataclasses.replace(self, repo_id=repo_id, hidden=list(self.hidden), d_hidden=list(self.d_hidden))


# --------------------------------------------------------------------------- pieces of the loop


class Agent:
    """The BC ensemble and D at one step: action (members' mean), doubt and D(s, a)."""

    def __init__(self, policy: BCPolicy, disc: Discriminator, obs_map: ObservationMap, device: torch.device) -> None:
        self.policy, self.disc, self.obs_map, self.device = policy, disc, obs_map, device
        self.keys = list(policy.features)

    def observe(self, env: Any, obs: np.ndarray) -> dict[str, np.ndarray]:
        return self.obs_map(env, obs)

    @torch.no_grad()
    def decide(self, features: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
        """(mean action, doubt) of the ensemble for one observation."""
        batch = {k: torch.as_tensor(features[k])[None].to(self.device) for k in self.keys}
        outs = self.policy.member_outputs(batch)
        return outs.mean(dim=0)[0].cpu().numpy().astype(np.float32), float(ensemble_doubt(outs)[0])

    def d_score(self, features: dict[str, np.ndarray], action: np.ndarray) -> float:
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
    """Signals of the policy's uninterrupted trajectory (executed part + look-ahead)."""
    trajectory: dict[str, np.ndarray]
    """That trajectory's policy inputs and actions (for re-scoring by a retrained D)."""
    policy_failed: bool
    """Whether that uninterrupted trajectory fails (the label of the ROC curves)."""
    feedback: list[str]
    intervened_at: int | None
    predictions: int


def run_episode(
    env: Any,
    seed: int,
    agent: Agent,
    predictor: Any,
    oracle: SimulatedOracle,
    d_ready: bool,
    features: dict[str, dict],
    fp_cooldown: int,
) -> EpisodeResult:
    """Thesis Algorithm 2, lines 3-34: one episode of policy, predictions, oracle and expert."""
    obs, info = env.reset(seed=seed)
    predictor.reset()
    oracle.start_episode()
    rows: list[dict[str, Any]] = []
    executed: list[dict[str, Any]] = []  # records of the policy's own steps
    expert, feedback, intervened_at, predictions, cooldown, t = None, [], None, 0, 0, 0
    success = False
    while not success:  # at least one step, even where the reset state already counts as solved
        feats = agent.observe(env, obs)
        request = False
        if expert is None:
            action, doubt = agent.decide(feats)
            d = agent.d_score(feats, action)
            executed.append({"d": d, "doubt": doubt, "frame": {**{k: feats[k] for k in agent.keys}, "action": action}})
            if cooldown > 0:
                cooldown -= 1
            elif predictor.predict(t, d if d_ready else None, doubt):
                request, predictions = True, predictions + 1
                if oracle.will_fail(env, obs, t):
                    feedback.append("tp")
                else:
                    feedback.append("fp")
                    cooldown = fp_cooldown
                predictor.feedback(feedback[-1])
            if not request and oracle.stops_unpredicted(env, obs, t):
                feedback.append("fn")
                predictor.feedback("fn")
            if feedback and feedback[-1] in ("tp", "fn") and intervened_at is None:
                intervened_at, expert = t, oracle.take_over(env)
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

    # the policy's uninterrupted trajectory: its executed steps, then the look-ahead that decided
    look = oracle.look_ahead
    if intervened_at is not None:
        signals, policy_failed = executed[:intervened_at] + look.records[intervened_at - look.start :], True
    else:
        signals, policy_failed = executed, not success
    trace = EpisodeTrace(
        d=np.array([s["d"] if d_ready else np.nan for s in signals]), doubt=np.array([s["doubt"] for s in signals])
    )
    frames = {k: np.stack([r[k] for r in rows]) for k in rows[0]}
    trajectory = {k: np.stack([s["frame"][k] for s in signals]) for k in signals[0]["frame"]}
    return EpisodeResult(frames, success, trace, trajectory, policy_failed, feedback, intervened_at, predictions)


def online_update(
    policy: BCPolicy, optimizers: list, expert: FrameBuffer, steps: int, args: FireArgs, rng, device
) -> float | None:
    """Algorithm 2 line 36: `steps` gradient steps of every member on batches of the expert set."""
    m, b = len(policy.members), args.batch_size
    policy.train()
    losses = []
    for _ in range(steps):
        batch = expert.sample(m * b, rng, device)
        losses += update_members(policy, optimizers, batch, b, [True] * m, args.online_lr)
    policy.eval()
    return float(np.mean(losses)) if losses else None


def retrain(policy: BCPolicy, optimizers: list, expert: FrameBuffer, args: FireArgs, seed: int, device) -> dict:
    """Algorithm 2 line 39: BC on the whole expert set, warm-started; each member keeps its weights of
    lowest loss on a seeded 20% hold-out of frames and stops after `retrain_patience` epochs without
    improvement."""
    n = len(expert)
    perm = np.random.default_rng([seed, n, 0xB0]).permutation(n)
    n_val = max(1, n // 5)
    val, train_rows = perm[:n_val], perm[n_val:]
    m = len(policy.members)
    b = min(args.batch_size, len(train_rows))
    val_batch = expert.gather(val, device)

    @torch.no_grad()
    def val_losses() -> list[float]:
        obs, target = policy.normalizer(val_batch), policy.normalizer.action(val_batch["action"])
        return [((net(obs) - target) ** 2).mean().item() for net in policy.members]

    policy.eval()
    best = val_losses()
    best_weights = [{k: v.clone() for k, v in net.state_dict().items()} for net in policy.members]
    bad, active, epoch = [0] * m, [True] * m, 0
    for epoch in range(args.retrain_max_epochs):
        policy.train()
        batches = [epoch_batches(len(train_rows), b, seed, member, epoch) for member in range(m)]
        for i in range(len(batches[0])):
            rows = np.concatenate([train_rows[batches[member][i]] for member in range(m)])
            update_members(policy, optimizers, expert.gather(rows, device), b, active, args.retrain_lr)
        policy.eval()
        for member, loss in enumerate(val_losses()):
            if not active[member]:
                continue
            if loss < best[member]:
                best[member], bad[member] = loss, 0
                best_weights[member] = {k: v.clone() for k, v in policy.members[member].state_dict().items()}
            else:
                bad[member] += 1
                active[member] = bad[member] < args.retrain_patience
        if not any(active):
            break
    for net, weights in zip(policy.members, best_weights, strict=True):
        net.load_state_dict(weights)
    return {"retrain_epochs": epoch + 1, "retrain_val_loss": float(np.mean(best)), "retrain_frames": n}


def thresholds(predictor: Any) -> dict[str, float]:
    """The current threshold(s) of a predictor, for the metrics."""
    if isinstance(predictor, OrRule):
        return {**thresholds(predictor.a), **thresholds(predictor.b)}
    if isinstance(predictor, BetaRule):
        return {"beta": predictor.beta}
    if isinstance(predictor, GDARule):
        return {"gamma": predictor.gamma, **({"beta": predictor.beta.beta} if predictor.beta else {})}
    return {"doubt_threshold": predictor.threshold}


def _save_npz(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> None:
    buf = io.BytesIO()
    np.savez(buf, __meta__=np.array(json.dumps(meta)), **arrays)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(buf.getvalue())
    os.replace(tmp, path)


def _load_npz(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "__meta__"}
        return arrays, json.loads(str(z["__meta__"]))


# --------------------------------------------------------------------------- the loop


def run(args: FireArgs) -> dict:
    """Run (or resume) FIRE and write the aggregated dataset; returns the final summary."""
    from shiftkit.envs import ENV_TASKS, env_family, make

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
    try:
        family = env_family(args.env)
        env_kwargs = dict(args.env_kwargs)
        if "control_hz" not in env_kwargs and fps in family.control_rates:
            env_kwargs["control_hz"] = fps
        env = make(args.env, args.task, **env_kwargs)
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(exc)) from None
    # Another registered env's dataset: its rate and observations are not this env's.
    recorded = sorted(recorded_envs(ds.root) & set(ENV_TASKS))
    if recorded and args.env not in recorded:
        env.close()
        raise ConfigError(
            f"{resolved.repo_id} was recorded in {', '.join(recorded)}, not {args.env}: "
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

    # --- BC initialised from the demonstrations (its own run folder, resumable too)
    bc_dir = run_dir.path / "bc-init"
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
    policy = load_policy(bc_dir, device=str(device))
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
    obs_map = ObservationMap(observed, list(env.observation_names))
    agent = Agent(policy, disc, obs_map, device)
    if args.doubt_threshold is None:
        with torch.no_grad():
            outs = policy.member_outputs(expert_set.gather(np.arange(len(expert_set)), device))
        doubt_threshold = float(ensemble_doubt(outs).max()) or 1e-6
    else:
        doubt_threshold = args.doubt_threshold
    predictor = make_predictor(args.predictor, doubt_threshold, beta=args.beta, gamma=args.gamma)
    roc_gda = GDARule(args.gamma)  # GDA statistics for the ROC scores, whichever predictor runs
    gda_rules = [roc_gda, *(r for r in (predictor, getattr(predictor, "a", None)) if isinstance(r, GDARule))]
    # the policy trajectories behind the GDA statistics, re-scored whenever D changes (window per outcome)
    history: dict[bool, deque] = {True: deque(maxlen=roc_gda.window), False: deque(maxlen=roc_gda.window)}
    margin = args.expert_margin if args.expert_margin is not None else math.ceil(1.5 * max(demo_lengths))
    oracle = SimulatedOracle(args.env, agent, check_step=max(0, env.max_episode_steps - margin))
    rng = np.random.default_rng([args.seed, 0xF12E])
    counters = {"episode": 0, "corrections": 0, "env_steps": 0, "since_retrain": 0, "wall_time": 0.0, "retrains": 0}
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
        policy.load_state_dict(state["policy"])
        for opt, s in zip(optimizers, state["optimizers"], strict=True):
            opt.load_state_dict(s)
        disc.load_state_dict(state["disc"])
        predictor.load_state_dict(state["predictor"])
        roc_gda.load_state_dict(state["roc_gda"])
        expert_set.load_state_dict(state["expert_set"])
        policy_set.load_state_dict(state["policy_set"])
        for failed, trajectories in state["history"].items():
            history[failed].extend(trajectories)
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        counters = state["counters"]
        oracle.forks, oracle.look_ahead_steps = state["oracle"]
    policy.eval()

    def checkpoint(summary: dict | None = None) -> None:
        step = counters["episode"]
        common = {"policy_spec": dataclasses.asdict(policy.spec), "model": policy.state_dict()}
        policy_run.save_checkpoint(step, {"trainer": "bc", "final": summary is not None, "metrics": None, **common})
        run_dir.save_checkpoint(
            step,
            {
                "trainer": "fire",
                "final": summary is not None,
                "summary": summary,
                "policy": policy.state_dict(),
                "optimizers": [o.state_dict() for o in optimizers],
                "disc": disc.state_dict(),
                "predictor": predictor.state_dict(),
                "roc_gda": roc_gda.state_dict(),
                "expert_set": expert_set.state_dict(),
                "policy_set": policy_set.state_dict(),
                "history": {failed: list(h) for failed, h in history.items()},
                "rng": rng.bit_generator.state,
                "torch_rng": torch.get_rng_state(),
                "counters": counters,
                "oracle": (oracle.forks, oracle.look_ahead_steps),
            },
        )

    # --- Algorithm 2: episodes until the expert's budget is spent
    from tqdm import tqdm

    bar = tqdm(
        total=args.budget_expert_samples,
        initial=min(counters["corrections"], args.budget_expert_samples),
        unit="correction",
        disable=not args.progress,
    )
    while counters["corrections"] < args.budget_expert_samples and (
        args.max_episodes is None or counters["episode"] < args.max_episodes
    ):
        i, started = counters["episode"], time.perf_counter()
        d_ready = disc.ready(len(policy_set))
        ep = run_episode(env, args.env_seed + i, agent, predictor, oracle, d_ready, observed, args.fp_cooldown)
        exec_time = time.perf_counter() - started
        n = len(ep.frames["action"])
        by_expert = ep.frames["source"][:, 0] == SOURCE_EXPERT
        keep = {k: ep.frames[k] for k in keys}
        expert_set.add({k: v[by_expert] for k, v in keep.items()})
        policy_set.add({k: v[~by_expert] for k, v in keep.items()})
        added = int(by_expert.sum())
        if ep.success and not by_expert[-1]:  # the final (s_T, a_T) of a success is expert data
            expert_set.add({k: v[-1:] for k, v in keep.items()})
            added += 1
        counters["corrections"] += int(by_expert.sum())
        bar.update(min(int(by_expert.sum()), args.budget_expert_samples - bar.n))
        counters["since_retrain"] += added
        counters["env_steps"] += n

        # scores for ROC curves, from statistics of earlier episodes only
        scores = {
            "beta": BetaRule().score(ep.trace),
            "gda": roc_gda.score(ep.trace),
            "doubt": float(np.max(ep.trace.doubt)) if len(ep.trace.doubt) else 0.0,
        }
        # --- learning (Algorithm 2, lines 35-40)
        predictor.update(ep.trace, ep.policy_failed)
        roc_gda.update(ep.trace, ep.policy_failed)
        history[ep.policy_failed].append(ep.trajectory)
        d_metrics = {}
        if disc.ready(len(policy_set)):
            d_metrics = disc.update(expert_set, policy_set, n, rng)
            rescored = {failed: [disc.score(x) for x in h] for failed, h in history.items()}
            for rule in gda_rules:
                rule.refit(rescored[True], rescored[False])
        bc_loss = online_update(policy, optimizers, expert_set, n, args, rng, device)
        retrained = {}
        if counters["since_retrain"] >= args.retrain_every:
            retrained = retrain(policy, optimizers, expert_set, args, args.seed + counters["retrains"], device)
            counters["since_retrain"] -= args.retrain_every
            counters["retrains"] += 1
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
        _save_npz(episodes_dir / f"episode_{i:06d}.npz", ep.frames, meta)
        run_dir.log(
            counters["episode"],
            "episode",
            episode=i,
            seed=args.env_seed + i,
            success=ep.success,
            policy_success=not ep.policy_failed,
            predictions=ep.predictions,
            feedback=ep.feedback,
            intervened_at=ep.intervened_at,
            length=n,
            episode_expert_samples=int(by_expert.sum()),
            corrections=counters["corrections"],
            expert_samples=len(expert_set),
            env_steps=counters["env_steps"],
            execution_time_s=counters["env_steps"] / fps,
            wall_time_s=counters["wall_time"],
            episode_exec_s=exec_time,
            look_ahead_steps=oracle.look_ahead_steps,
            forks=oracle.forks,
            d_ready=d_ready,
            scores=scores,
            thresholds=thresholds(predictor),
            bc_loss=bc_loss,
            **d_metrics,
            **retrained,
        )
        if args.eval_every and counters["episode"] % args.eval_every == 0:
            results = run_episodes(policy, env, args.eval_episodes, EVAL_SEED)
            wins = sum(r.success for r in results)
            run_dir.log(
                counters["episode"],
                "eval",
                success_rate=wins / len(results),
                ci95=list(wilson_interval(wins, len(results))),
                episodes=len(results),
                expert_samples=len(expert_set),
                corrections=counters["corrections"],
                execution_time_s=counters["env_steps"] / fps,
                wall_time_s=counters["wall_time"],
            )
        checkpoint()

    bar.close()
    # --- the rollouts as lerobot's DAgger strategy records them, then offline FIRE over them: the
    # aggregated dataset, predictor file and ROC come from the same code a lab runs on its recordings
    summary = _summary(run_dir, counters, len(expert_set))
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
    env.close()
    return summary


def aggregate_args(args: FireArgs, rollouts: list[str], policy: str, out: Path) -> AggregateArgs:
    """The offline aggregation of a simulated run's recordings, with the run's settings."""
    return AggregateArgs(
        expert=args.dataset,
        root=args.root,
        rollouts=rollouts,
        out=str(out),
        repo_id=args.repo_id,
        policy=policy,
        predictor=args.predictor if args.predictor in RULES else "gda",
        seed=args.seed,
        d_hidden=list(args.d_hidden),
        d_lr=args.d_lr,
        grad_penalty=args.grad_penalty,
        beta=args.beta,
        gamma=args.gamma,
        fp_cooldown=args.fp_cooldown,
        device=args.device,
    )


def _summary(run_dir: RunDir, counters: dict, expert_samples: int) -> dict:
    lines = [x for x in run_dir.read_metrics() if x["split"] == "episode"]
    feedback = [f for x in lines for f in x["feedback"]]
    return {
        "episodes": counters["episode"],
        "successes": sum(x["success"] for x in lines),
        "policy_successes": sum(x["policy_success"] for x in lines),
        "corrections": counters["corrections"],
        "expert_samples": expert_samples,
        "env_steps": counters["env_steps"],
        "true_positives": feedback.count("tp"),
        "false_positives": feedback.count("fp"),
        "false_negatives": feedback.count("fn"),
        "retrains": counters["retrains"],
    }


def recorded_episodes(episodes_dir: Path, fps: int, task: str) -> Iterator[Episode]:
    """The executed episodes as a DAgger recording holds them (every frame, in order)."""
    for path in sorted(episodes_dir.glob("episode_*.npz")):
        frames, _ = _load_npz(path)
        n = len(frames["action"])
        frames["timestamp"] = (np.arange(n) / fps).astype(np.float32)
        frames["task"] = np.array([task] * n)
        yield Episode(frames)


# --------------------------------------------------------------------------- reading runs


def read_episode_lines(run_path: str | Path) -> list[dict]:
    """The per-episode metric lines of a FIRE run; ShiftkitError (one line) for anything else."""
    from shiftkit.pipelines.errors import ShiftkitError

    run_dir = RunDir(Path(run_path), resume=True)
    config = run_dir.read_config() if (Path(run_path) / "config.json").is_file() else None
    if config is None or config.get("trainer") != "fire":
        raise ShiftkitError(f"{run_path} is not a FIRE run folder (no config.json of trainer 'fire')")
    try:
        lines = [x for x in run_dir.read_metrics() if x.get("split") == "episode"]
    except (json.JSONDecodeError, KeyError) as exc:
        raise ShiftkitError(f"{run_path}: unreadable metrics.jsonl ({exc})") from None
    if not lines:
        raise ShiftkitError(f"FIRE run {run_path} has no finished episode yet")
    return lines


def roc_scores(lines: list[dict]) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Per-predictor episode scores (beta, gda, doubt and the quantile OR of gda and doubt) and the
    labels (the policy's uninterrupted run failed) of the episodes after D started."""
    from shiftkit.policies.failure_predictors import quantile_or

    ready = [x for x in lines if x["d_ready"]]
    scores = {name: np.array([x["scores"][name] for x in ready], dtype=float) for name in ("beta", "gda", "doubt")}
    scores["gda+doubt"] = quantile_or(scores["gda"], scores["doubt"])
    return scores, np.array([not x["policy_success"] for x in ready])


def success_curve(
    lines: list[dict], x_key: str, window: int = 10
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(x, success rate, 95% low, high) of the policy's own outcome over a moving window of episodes
    (each FIRE episode's label is an evaluation of the policy of that time, see `run_episode`)."""
    x = np.array([line[x_key] for line in lines], dtype=float)
    ok = np.array([line["policy_success"] for line in lines], dtype=float)
    rate, low, high = [], [], []
    for i in range(len(ok)):
        part = ok[max(0, i - window + 1) : i + 1]
        lo, hi = wilson_interval(int(part.sum()), len(part))
        rate.append(part.mean())
        low.append(lo)
        high.append(hi)
    return x, np.array(rate), np.array(low), np.array(high)
