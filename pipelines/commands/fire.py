"""`shiftkit fire`: interactive imitation with failure prediction and a simulated expert (FIRE, thesis ch. 5)."""

from __future__ import annotations

import argparse

from shiftkit.pipelines.dataclass_config import add_env_kwarg, int_list

HELP = (
    "FIRE: run a BC policy with failure prediction and simulated expert interventions; "
    "`fire aggregate`: FIRE over recorded DAgger rollouts"
)
# the online loop's options that `fire aggregate` does without (checked in `run`)
REQUIRED = ("dataset", "env", "task", "output")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", help="dataset ID or local folder of the initial demonstrations (required)")
    p.add_argument("--root", help="local folder of the dataset")
    p.add_argument("--env", help="registered environment with a scripted expert, e.g. panda-play (required)")
    p.add_argument("--task", help="task of the environment, e.g. stack (required)")
    p.add_argument(
        "--predictor", choices=("beta", "gda", "doubt", "gda+doubt"), default="gda", help="failure predictor"
    )
    p.add_argument(
        "--budget-expert-samples", type=int, default=2000, help="stop once the expert corrected this many steps"
    )
    p.add_argument("--max-episodes", type=int, help="stop after this many episodes at the latest")
    p.add_argument("--output", help="run folder (config, metrics, checkpoints, policy, episodes) (required)")
    p.add_argument("--repo-id", help="repo ID of the aggregated dataset (default: local/<output folder name>)")
    p.add_argument("--dataset-root", help="folder of the aggregated dataset (default: $HF_LEROBOT_HOME/<repo-id>)")
    add_env_kwarg(p, "control_hz=10")
    p.add_argument("--seed", type=int, default=0, help="seed of BC, D, sampling (default: 0)")
    p.add_argument("--env-seed", type=int, default=10000, help="episode i resets with ENV_SEED+i (default: 10000)")
    p.add_argument("--bc-regime", choices=("early-stop", "fixed"), default="early-stop", help="initial BC regime")
    p.add_argument("--bc-steps", type=int, help="initial BC steps (fixed regime; a bound for early-stop)")
    p.add_argument("--ensemble", type=int, default=5, help="BC ensemble members (default: 5)")
    p.add_argument("--hidden", type=int_list, default=[256, 256], help="BC widths, comma-separated (default: 256,256)")
    p.add_argument("--batch-size", type=int, default=64, help="BC batch per member (default: 64)")
    p.add_argument("--retrain-every", type=int, default=500, help="d: full BC retraining every d expert samples")
    p.add_argument("--d-start", type=int, default=10000, help="policy samples before D trains (default: 10000)")
    p.add_argument("--d-hidden", type=int_list, default=[256, 256], help="D widths, comma-separated (default: 256,256)")
    p.add_argument("--beta", type=int, default=20, help="initial beta of the beta rule (default: 20)")
    p.add_argument("--gamma", type=float, default=0.5, help="initial GDA posterior threshold (default: 0.5)")
    p.add_argument("--doubt-threshold", type=float, help="initial doubt threshold (default: max over the demos)")
    p.add_argument("--expert-margin", type=int, help="steps the expert needs (default: 1.5x longest demo)")
    p.add_argument("--eval-every", type=int, default=0, help="evaluate the policy every N episodes (default: never)")
    p.add_argument("--eval-episodes", type=int, default=10, help="episodes per evaluation (default: 10)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda (default: auto)")
    p.add_argument("--threads", type=int, help="CPU threads for torch")
    p.add_argument("--resume", action="store_true", help="continue the run in --output after its last episode")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    sub = p.add_subparsers(dest="fire_action", metavar="aggregate")
    _add_aggregate(sub.add_parser("aggregate", help=AGGREGATE_HELP, description=AGGREGATE_HELP))


AGGREGATE_HELP = (
    "offline FIRE over lerobot DAgger recordings: label frames, train D, fit the beta and GDA rules, "
    "write the aggregated dataset with a failure predictor file and ROC scores"
)


def _add_aggregate(p: argparse.ArgumentParser) -> None:
    p.add_argument("--expert", required=True, help="dataset ID or local folder of the expert demonstrations")
    p.add_argument("--root", help="local folder of the expert dataset")
    p.add_argument(
        "--rollouts", required=True, nargs="+", metavar="ID", help="DAgger recordings (lerobot-rollout, either layout)"
    )
    p.add_argument("--out", required=True, help="folder of the aggregated dataset (must not exist)")
    p.add_argument("--repo-id", required=True, help="repo ID of the aggregated dataset")
    p.add_argument("--policy", help="BC run folder of the policy that ran the rollouts (D uses its inputs)")
    p.add_argument("--predictor", choices=("beta", "gda"), default="gda", help="rule of the predictor file")
    p.add_argument("--seed", type=int, default=0, help="seed of D (default: 0)")
    p.add_argument("--d-steps", type=int, help="D gradient steps (default: one per recorded frame)")
    p.add_argument("--d-hidden", type=int_list, default=[256, 256], help="D widths, comma-separated (default: 256,256)")
    p.add_argument("--beta", type=int, default=20, help="initial beta of the beta rule (default: 20)")
    p.add_argument("--gamma", type=float, default=0.5, help="initial GDA posterior threshold (default: 0.5)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda (default: auto)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_aggregate(args: argparse.Namespace) -> int:
    from shiftkit.policies.fire_aggregate import AggregateArgs, aggregate

    summary = aggregate(
        AggregateArgs(
            expert=args.expert,
            root=args.root,
            rollouts=list(args.rollouts),
            out=args.out,
            repo_id=args.repo_id,
            policy=args.policy,
            predictor=args.predictor,
            seed=args.seed,
            d_steps=args.d_steps,
            d_hidden=args.d_hidden,
            beta=args.beta,
            gamma=args.gamma,
            device=args.device,
            progress=not args.no_progress,
        )
    )
    auc = ", ".join(
        f"{k} {v:.3f}" if v is not None else f"{k} n/a (one outcome only)" for k, v in summary["auc"].items()
    )
    print(
        f"FIRE aggregate: {summary['episodes']} episodes, {summary['corrections']} corrected frames, "
        f"{summary['stretches']} policy stretches ({summary['failed_stretches']} ended in a correction); "
        f"ROC AUC against the recorded interventions: {auc}; dataset {summary['dataset']}, "
        f"predictor {summary['predictor']}"
    )
    return 0


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from shiftkit.pipelines.errors import ConfigError
    from shiftkit.pipelines.hub import validate_repo_id
    from shiftkit.pipelines.option_values import check_env_kwargs
    from shiftkit.pipelines.staging import DestinationLock
    from shiftkit.policies.fire import FireArgs
    from shiftkit.policies.fire import run as run_fire

    if args.fire_action == "aggregate":
        return _run_aggregate(args)
    missing = [f"--{name}" for name in REQUIRED if getattr(args, name) is None]
    if missing:
        raise ConfigError(f"the following arguments are required: {', '.join(missing)}")
    # the default repo id meets the rules an explicit one does, before any work
    validate_repo_id(args.repo_id or f"local/{Path(args.output).name}")
    check_env_kwargs(args.env, dict(args.env_kwarg))

    with DestinationLock(Path(args.output)):  # a second run on the same --output is told who holds it
        summary = run_fire(
            FireArgs(
                dataset=args.dataset,
                root=args.root,
                env=args.env,
                task=args.task,
                output_dir=args.output,
                predictor=args.predictor,
                budget_expert_samples=args.budget_expert_samples,
                max_episodes=args.max_episodes,
                repo_id=args.repo_id,
                dataset_root=args.dataset_root,
                env_kwargs=dict(args.env_kwarg),
                seed=args.seed,
                env_seed=args.env_seed,
                bc_regime=args.bc_regime,
                bc_steps=args.bc_steps,
                ensemble_size=args.ensemble,
                hidden=args.hidden,
                batch_size=args.batch_size,
                retrain_every=args.retrain_every,
                d_start=args.d_start,
                d_hidden=args.d_hidden,
                beta=args.beta,
                gamma=args.gamma,
                doubt_threshold=args.doubt_threshold,
                expert_margin=args.expert_margin,
                eval_every=args.eval_every,
                eval_episodes=args.eval_episodes,
                device=args.device,
                threads=args.threads,
                resume=args.resume,
                progress=not args.no_progress,
            )
        )
    print(
        f"FIRE: {summary['episodes']} episodes ({summary['successes']} successful, the policy alone "
        f"{summary['policy_successes']}), {summary['corrections']} expert corrections "
        f"(predictions: {summary['true_positives']} agreed, {summary['false_positives']} refused; "
        f"{summary['false_negatives']} unpredicted failures); dataset {summary['dataset']}"
    )
    return 0
