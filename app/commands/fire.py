"""`shiftkit fire`: interactive imitation with failure prediction and a simulated expert (FIRE, thesis ch. 5).

The options of `fire` and `fire aggregate` are generated from `FireArgs` and `AggregateArgs`
(`dataclass_config.DataclassOptions`): help, defaults and types come from the dataclasses.
"""

from __future__ import annotations

import argparse

from shiftkit.datasets.option_values import DataclassOptions

HELP = (
    "FIRE: run a BC policy with failure prediction and simulated expert interventions; "
    "`fire aggregate`: FIRE over recorded DAgger rollouts"
)
AGGREGATE_HELP = (
    "offline FIRE over lerobot DAgger recordings: label frames, train D, fit the beta and GDA rules, "
    "write the aggregated dataset with a failure predictor file and ROC scores"
)


def _fire_options() -> DataclassOptions:
    from shiftkit.policies.fire.config import FireArgs, FireBC
    from shiftkit.policies.trainers.bc.args import FLAGS

    return DataclassOptions(
        FireArgs,
        flags={"output_dir": "output", "env_kwargs": "env-kwarg"},
        cli_defaults={"progress": True},
        nested={"bc": DataclassOptions(FireBC, flags=FLAGS)},  # `--bc.ensemble` as `train bc --ensemble`
    )


def _aggregate_options() -> DataclassOptions:
    from shiftkit.policies.fire.config import AggregateArgs

    return DataclassOptions(AggregateArgs, cli_defaults={"progress": True})


def add_arguments(p: argparse.ArgumentParser, argv: list[str] | None = None) -> None:
    """The options of `fire`, and of `fire aggregate` only when it is chosen (`argv`: the words
    after `fire`; None builds both)."""
    _fire_options().add_to(p)
    sub = p.add_subparsers(dest="fire_action", metavar="aggregate")
    aggregate = sub.add_parser("aggregate", help=AGGREGATE_HELP, description=AGGREGATE_HELP)
    if argv is None or "aggregate" in argv:
        _aggregate_options().add_to(aggregate)


def _run_aggregate(args: argparse.Namespace) -> int:
    from shiftkit.policies.fire.aggregate import aggregate

    summary = aggregate(_aggregate_options().build(args))
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
    """Run FIRE (or `fire aggregate`) and print its counts; return the exit code."""
    from pathlib import Path

    from shiftkit.app.env_kwargs import check_env_kwargs
    from shiftkit.datasets.hub import validate_repo_id
    from shiftkit.datasets.staging import DestinationLock
    from shiftkit.policies.fire.loop import run as run_fire

    if getattr(args, "fire_action", None) == "aggregate":
        return _run_aggregate(args)
    config = _fire_options().build(args)
    # the default repo id meets the rules an explicit one does, before any work
    validate_repo_id(config.repo_id or f"local/{Path(config.output_dir).name}")
    check_env_kwargs(config.env, config.env_kwargs)

    with DestinationLock(Path(config.output_dir)):  # a second run on the same --output is told who holds it
        summary = run_fire(config)
    print(
        f"FIRE: {summary['episodes']} episodes ({summary['warm_up_episodes']} of warm-up; {summary['successes']} "
        f"successful, the policy alone {summary['policy_successes']}), {summary['corrections']} expert corrections "
        f"in {summary['interventions']} interventions ({summary['hand_backs']} handed back to the policy; "
        f"predictions: {summary['true_positives']} agreed, {summary['false_positives']} refused; "
        f"{summary['false_negatives']} unpredicted failures stopped); dataset {summary['dataset']}"
    )
    return 0
