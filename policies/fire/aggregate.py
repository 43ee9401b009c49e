"""Offline FIRE (thesis ch. 5) over recorded human-in-the-loop rollouts: `shiftkit fire aggregate`.

Inputs: the expert demonstrations and any number of lerobot DAgger recordings (`dagger_recording`:
either layout). Every frame gets a source: demonstration (0), policy (1: `intervention` False) or
expert correction (2: True). Each stretch of policy frames is one trajectory of the policy, a failure
when a correction follows it (the operator took over), a success when it runs to its episode's end;
the operator handing control back shows as a correction followed by policy frames.

Then, with the code of the simulated loop (`discriminator`, `failure_predictors`):
1. D(s, a) trains on expert frames (demonstrations + corrections) against the policy's frames, for
   as many steps as the recordings hold frames (the simulated loop's rule: one step per frame); with
   only corrections recorded, the policy's samples are its own actions at the corrected states;
2. the beta and GDA rules are fitted by replaying the stretches in recording order, as the loop
   learns from its executed segments: each policy stretch is scored with the statistics of the
   earlier ones (as the loop scores an episode before learning from it), then the rule predicts step
   by step (the episode's step count, which GDA's statistics are indexed by), answered as the
   recording answers (a request in a stretch that ends in a correction: agreed; otherwise refused; a
   correction nobody predicted: missed); then the stretch joins GDA's statistics (corrections as
   successful data, as in the reference) and GDA re-derives its threshold from their ROC;
3. the aggregated LeRobot dataset: the demonstrations and every recorded episode, with per-frame
   `intervention` (as lerobot writes it), `source`, `discriminator_score` (final D) and
   `intervention_request` (where the chosen rule, as fitted up to then, asked); beside it, in
   `meta/`, the predictor file (`fire.predictor`) and each rule's ROC scores (`fire_roc.json`,
   drawn by `shiftkit plot roc`).

D is scored on the recordings it trained on, so its ROC is in-sample for D (not for the rules'
statistics). A recording's episodes rotated mid-task by time count their last stretch as a success.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shiftkit.datasets.dataset import open as resolve_dataset
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import numpy_dtype, vector_feature
from shiftkit.datasets.ids import dataset_fingerprint
from shiftkit.datasets.jsonutil import dumps, read_json_file
from shiftkit.datasets.reader import open_lerobot_dataset
from shiftkit.datasets.staging import check_inputs_and_outputs
from shiftkit.datasets.writer import write_episodes
from shiftkit.policies.bc_policy import PolicySpec, is_image_feature, load_policy
from shiftkit.policies.fire.config import AggregateArgs
from shiftkit.policies.fire.dagger_recording import INTERVENTION, INTERVENTION_FEATURE, open_recordings, runs
from shiftkit.policies.fire.discriminator import Discriminator, DiscriminatorConfig
from shiftkit.policies.fire.failure_predictors import BetaRule, EpisodeTrace, GDARule, Segment, roc_curve
from shiftkit.policies.fire.predictor import FailurePredictor
from shiftkit.policies.frame_buffer import FrameBuffer
from shiftkit.policies.run_dir import run_folder, torch_device
from shiftkit.policies.trainers.bc.args import BCSettings

SOURCE_DEMO, SOURCE_POLICY, SOURCE_EXPERT = 0, 1, 2
# per-frame features of the aggregated dataset besides the recordings' own
FIRE_FEATURES = {
    INTERVENTION: INTERVENTION_FEATURE,
    "source": vector_feature("int64", ["source"]),
    "discriminator_score": vector_feature("float32", ["discriminator_score"]),
    "intervention_request": vector_feature("bool", ["intervention_request"]),
}
PREDICTOR_FILE = "meta/failure_predictor.pt"
ROC_FILE = "meta/fire_roc.json"


def _spec(args: AggregateArgs, expert_root: Path, features: dict[str, dict]) -> PolicySpec:
    """D's inputs and normalisation: the rollout policy's, else the demonstrations' observations."""
    if args.policy is not None:
        spec = load_policy(args.policy).spec
        missing = [k for k in [*spec.features, "action"] if k not in features]
        if missing:
            raise DatasetError(f"the recordings lack the policy input {missing[0]!r}")
        # a policy trained on another env's data may share the names but not the sizes
        for key, ft in {**spec.features, "action": spec.action}.items():
            want, got = (tuple(ft["shape"]), ft["dtype"]), (tuple(features[key]["shape"]), features[key]["dtype"])
            if want != got:
                raise DatasetError(
                    f"--policy {args.policy} reads {key!r} as {want[1]} {list(want[0])}, the recordings hold "
                    f"{got[1]} {list(got[0])}: it was trained on other data (another env?) than these rollouts"
                )
        return spec
    keys = [k for k in features if k.startswith("observation.")]
    if not keys:
        raise DatasetError("the recordings have no observation.* features")
    stats_path = expert_root / "meta" / "stats.json"
    stats = read_json_file(stats_path, "dataset statistics") if stats_path.is_file() else {}
    lacking = [k for k in [*keys, "action"] if "mean" not in stats.get(k, {}) or "std" not in stats.get(k, {})]
    if lacking:
        raise DatasetError(f"{stats_path} lacks mean/std of {lacking[0]!r}")
    defaults = BCSettings()
    pick = lambda ft: {f: ft.get(f) for f in ("dtype", "shape", "names")}  # noqa: E731
    return PolicySpec(
        features={k: pick(features[k]) for k in keys},
        action=pick(features["action"]),
        stats={k: {"mean": stats[k]["mean"], "std": stats[k]["std"]} for k in [*keys, "action"]},
        encoder=defaults.encoder,
        num_keypoints=defaults.num_keypoints,
        hidden=defaults.hidden,
        ensemble_size=1,
    )


def _d_inputs(frames: dict[str, np.ndarray], keys: list[str], spec: PolicySpec) -> dict[str, np.ndarray]:
    out = {}
    for k in keys:
        ft = spec.action if k == "action" else spec.features[k]
        out[k] = frames[k] if is_image_feature(ft) else np.asarray(frames[k], dtype=np.float32)
    return out


@dataclass
class Stretch:
    """One stretch of policy frames or of a correction inside a recorded episode."""

    episode: int
    """Index among all recorded episodes (recordings in order)."""
    start: int
    end: int
    failed: bool
    """A policy stretch that ends in a correction."""
    expert: bool = False
    """A correction (the operator drove)."""


def stretches(intervention: np.ndarray, episode: int) -> list[Stretch]:
    """The stretches of one episode in order (`intervention` per frame)."""
    parts = runs(intervention)
    return [Stretch(episode, s, e, not on and k + 1 < len(parts), on) for k, (s, e, on) in enumerate(parts)]


def replay(rule: Any, d: np.ndarray, start: int, failed: bool, cooldown: int) -> np.ndarray:
    """Run `rule` along one policy stretch starting at episode step `start`, answered by the
    recording; the steps where it asked."""
    asked = np.zeros(len(d), dtype=bool)
    rule.reset()
    wait = 0
    for i, d_t in enumerate(d):
        t = start + i
        if wait > 0:
            wait -= 1
            rule.predict(t, float(d_t))  # the watch goes on, its requests are not heard (5.3.2)
            continue
        if rule.predict(t, float(d_t)):
            asked[i] = True
            rule.feedback("tp" if failed else "fp")
            if failed:  # the operator takes over here
                break
            wait = cooldown
    if failed and not asked.any():
        rule.feedback("fn")
    return asked


def fit_rules(
    traces: list[np.ndarray], parts: list[Stretch], args: AggregateArgs
) -> tuple[dict[str, Any], dict[str, list[float]], list[np.ndarray]]:
    """Fit the beta and GDA rules by replaying the stretches (`parts`, with their D values `traces`)
    in order, as the simulated loop learns from its executed segments; returns the rules, each rule's
    per-policy-stretch ROC score (from earlier stretches only) and the chosen rule's requests there.
    A policy stretch counts towards GDA's failure prior unless it is a success that follows a
    correction (the reference counts the policy's own attempts)."""
    rules = {"beta": BetaRule(args.beta), "gda": GDARule(args.gamma)}
    gda = rules["gda"]
    scores: dict[str, list[float]] = {"beta": [], "gda": []}
    requests = []
    for d, part in zip(traces, parts, strict=True):
        if not part.expert:
            trace = EpisodeTrace(d=d, doubt=np.zeros(len(d)))
            scores["beta"].append(BetaRule().score(trace))
            scores["gda"].append(gda.score(trace, part.start))
            asked = {name: replay(rule, d, part.start, part.failed, args.fp_cooldown) for name, rule in rules.items()}
            requests.append(asked[args.predictor])
            if part.failed or part.start == 0:
                gda.add_outcome(part.failed)
        gda.add_segment(Segment(part.start, part.failed, part.expert, d=np.asarray(d, dtype=np.float64)))
    return rules, scores, requests


def aggregate(args: AggregateArgs) -> dict[str, Any]:
    """Aggregate demonstrations and DAgger recordings; returns a summary (episodes, frames, AUCs)."""
    from tqdm import tqdm

    args.check()
    out = Path(args.out)
    if out.exists():
        raise ConfigError(f"aggregated dataset destination already exists: {out}")
    device = torch_device(args.device)
    expert_resolved = resolve_dataset(args.expert, root=args.root)
    expert = open_lerobot_dataset(expert_resolved.root)
    check_inputs_and_outputs(
        [
            ("--expert", expert_resolved.root),
            *(("--rollouts", resolve_dataset(ref).root) for ref in args.rollouts),
            *([("--policy", run_folder(args.policy))] if args.policy is not None else []),
        ],
        [("--out", out)],
        content_key=dataset_fingerprint,
    )
    recordings = open_recordings(args.rollouts, expert.fps, expert.features)
    features = {k: v for k, v in recordings[0].reader.features.items() if k != INTERVENTION}
    if "action" not in features:
        raise DatasetError(f"rollouts {recordings[0].name} have no 'action' feature")
    spec = _spec(args, expert_resolved.root, features)
    keys = [*spec.features, "action"]

    # --- expert set (demonstrations + corrections) and policy set; stretches per recorded episode
    expert_set, policy_set = FrameBuffer(keys), FrameBuffer(keys)
    for demo in expert.iter_episodes():
        expert_set.add(_d_inputs(demo.frames, keys, spec))
    parts: list[Stretch] = []
    index = corrections = 0
    layouts = []  # per recording: whether the policy drove any of its frames
    for rec in recordings:
        before = len(policy_set)
        for ep in rec.reader.iter_episodes():
            flags = np.asarray(ep.frames[INTERVENTION], dtype=bool).reshape(-1)
            inputs = _d_inputs(ep.frames, keys, spec)
            expert_set.add({k: v[flags] for k, v in inputs.items()})
            policy_set.add({k: v[~flags] for k, v in inputs.items()})
            parts += stretches(flags, index)
            corrections += int(flags.sum())
            index += 1
        layouts.append("continuous" if len(policy_set) > before else "corrections")
    if len(policy_set) == 0:
        # only corrections were recorded: D compares them with what the policy would have done there
        if args.policy is None:
            raise DatasetError(
                "the recordings hold no policy frames (only corrections: record_autonomous=false); pass "
                "--policy RUN (the policy that ran them) so D can compare the corrections with its actions"
            )
        policy = load_policy(args.policy)
        with torch.no_grad():
            for rec in recordings:
                for ep in rec.reader.iter_episodes():
                    inputs = _d_inputs(ep.frames, keys, spec)
                    batch = {k: torch.as_tensor(np.array(inputs[k])) for k in spec.features}  # a writable copy
                    policy_set.add({**inputs, "action": policy(batch).numpy().astype(np.float32)})
        own_actions = True
    else:
        own_actions = False

    # --- D (the simulated loop's discriminator and update)
    disc = Discriminator(
        spec,
        DiscriminatorConfig(hidden=list(args.d_hidden), lr=args.d_lr, grad_penalty=args.grad_penalty),
        device,
        seed=args.seed,
    )
    rng = np.random.default_rng([args.seed, 0xD15C])
    steps = args.d_steps or (corrections if own_actions else len(policy_set) + corrections)
    with tqdm(total=steps, unit="D step", disable=not args.progress) as bar:
        for done in range(0, steps, 256):
            disc.update(expert_set, policy_set, min(256, steps - done), rng)
            bar.update(min(256, steps - done))
    del expert_set, policy_set

    # --- D's scores of every recorded frame, the rules fitted on the policy stretches
    scores_by_episode = []
    for rec in recordings:
        for ep in rec.reader.iter_episodes():
            scores_by_episode.append(disc.score(_d_inputs(ep.frames, keys, spec)))
    traces = [scores_by_episode[p.episode][p.start : p.end] for p in parts]
    rules, roc, requests = fit_rules(traces, parts, args)
    policy_parts = [p for p in parts if not p.expert]
    asked = [np.zeros(len(s), dtype=bool) for s in scores_by_episode]
    for p, r in zip(policy_parts, requests, strict=True):
        asked[p.episode][p.start : p.end] = r

    # --- the predictor file and the ROC of the policy stretches, written into the dataset folder
    predictor = FailurePredictor(disc, spec, rules, args.predictor, expert.fps)
    labels = [p.failed for p in policy_parts]
    aucs = {}
    for name, values in roc.items():
        try:
            aucs[name] = roc_curve(np.array(values), np.array(labels))[2]
        except ValueError:
            aucs[name] = None
    roc_text = dumps({"failed": labels, "scores": roc, "auc": aucs, "stretches": len(policy_parts)}) + "\n"

    # --- the aggregated dataset, streamed episode by episode
    schema = {**features, **FIRE_FEATURES}

    def episodes() -> Iterator[Episode]:
        for demo in expert.iter_episodes():
            n = len(demo)
            frames = {k: demo.frames[k] for k in [*features, "timestamp", "task"]}
            frames.update(
                {
                    INTERVENTION: np.zeros((n, 1), dtype=bool),
                    "source": np.full((n, 1), SOURCE_DEMO, dtype=np.int64),
                    "discriminator_score": disc.score(_d_inputs(demo.frames, keys, spec)).astype(np.float32)[:, None],
                    "intervention_request": np.zeros((n, 1), dtype=bool),
                }
            )
            yield Episode(frames, {"fire": {"source": "demonstration"}})
        index = 0
        for rec in recordings:
            for ep in rec.reader.iter_episodes():
                flags = np.asarray(ep.frames[INTERVENTION], dtype=bool).reshape(-1, 1)
                frames = {k: ep.frames[k] for k in [*features, "timestamp", "task"]}
                frames.update(
                    {
                        INTERVENTION: flags,
                        "source": np.where(flags, SOURCE_EXPERT, SOURCE_POLICY).astype(np.int64),
                        "discriminator_score": scores_by_episode[index].astype(np.float32)[:, None],
                        "intervention_request": asked[index][:, None],
                    }
                )
                frames = {
                    k: np.asarray(v, dtype=numpy_dtype(schema[k])) if k in schema else v for k, v in frames.items()
                }
                meta = {
                    "fire": {
                        "source": "rollout",
                        "recording": rec.name,
                        "episode": int(ep.meta.get("source_episode_index", 0)),
                    }
                }
                yield Episode(frames, meta)
                index += 1

    written, _ = write_episodes(
        args.repo_id,
        out,
        expert.fps,
        schema,
        episodes(),
        robot_type=expert.robot_type,
        sources=[
            {"kind": "lerobot", "path": str(expert_resolved.root), "num_episodes": expert.num_episodes},
            *(
                {
                    "kind": "dagger",
                    "path": str(r.resolved.root),
                    "layout": layout,
                    "num_episodes": r.reader.num_episodes,
                }
                for r, layout in zip(recordings, layouts, strict=True)
            ),
        ],
        seed=args.seed,
        files={PREDICTOR_FILE: predictor.save, ROC_FILE: lambda path: path.write_text(roc_text)},
        fire={
            "predictor": args.predictor,
            "d_steps": steps,
            "policy": args.policy,
            # D's policy samples: the recorded policy frames, or the policy's own actions
            # at the corrected states when only corrections were recorded
            "d_policy_samples": "policy actions at corrected states" if own_actions else "recorded",
        },
    )
    return {
        "dataset": str(out),
        "episodes": written,
        "stretches": len(policy_parts),
        "failed_stretches": int(sum(labels)),
        "corrections": corrections,
        "auc": aucs,
        "predictor": str(out / PREDICTOR_FILE),
    }


def read_roc(path: str | Path) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The per-stretch ROC scores and labels an aggregated dataset keeps in `meta/fire_roc.json`."""
    data = read_json_file(Path(path) / ROC_FILE, "FIRE ROC scores")
    try:
        return {k: np.asarray(v, dtype=float) for k, v in data["scores"].items()}, np.asarray(
            data["failed"], dtype=bool
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{Path(path) / ROC_FILE}: malformed ({exc})") from None
