"""`shiftkit train bc|vpace|lfgp`: train a policy from dataset IDs into a run folder."""

from __future__ import annotations

import argparse
import importlib.util

from shiftkit.pipelines.dataclass_config import csv_list
from shiftkit.pipelines.option_values import finite_float, non_negative_int, positive_float, positive_int

HELP = "train a policy (bc, vpace, lfgp) from LeRobot dataset IDs"

# `train vpace` / `train lfgp` come from the VPACE trainer's own CLI module when it is installed
VPACE_CLI = "shiftkit.policies.vpace_cli"


def _add_bc_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", required=True, help="dataset ID(s) or local folder(s), comma-separated")
    p.add_argument("--root", help="local folder of the dataset (one dataset)")
    p.add_argument("--output", required=True, help="run folder (config, checkpoints, metrics, model card)")
    p.add_argument(
        "--regime",
        choices=("early-stop", "fixed"),
        default="early-stop",
        help="early-stop: 20%% hold-out, patience 30, max 200 epochs, Adam 1e-3; "
        "fixed: --steps (20000) with weight decay 0.1, lr 3e-4 halved midway",
    )
    p.add_argument(
        "--steps",
        type=positive_int,
        help="gradient steps: exactly this many with --regime fixed (default 20000); with early-stop an upper "
        "bound (default: --max-epochs epochs), training ends sooner once every member stops improving",
    )
    p.add_argument("--max-epochs", type=positive_int, default=200, help="early-stop: most epochs (default: 200)")
    p.add_argument(
        "--patience", type=positive_int, default=30, help="early-stop: epochs without improvement (default: 30)"
    )
    p.add_argument("--batch-size", type=positive_int, default=64, help="frames per step and member (default: 64)")
    p.add_argument("--lr", type=positive_float, help="learning rate (default: 1e-3 early-stop, 3e-4 fixed)")
    p.add_argument("--weight-decay", type=finite_float, help="AdamW weight decay (default: 0 early-stop, 0.1 fixed)")
    p.add_argument(
        "--val-fraction", type=finite_float, help="held-out episode share (default: 0.2 early-stop, 0 fixed)"
    )
    p.add_argument("--ensemble", type=positive_int, default=5, help="ensemble members (default: 5)")
    p.add_argument("--inputs", type=csv_list, help="observation features to use, comma-separated (default: all)")
    p.add_argument("--encoder", choices=("cnn", "resnet18"), default="cnn", help="image encoder (default: cnn)")
    p.add_argument("--encoder-weights", help="local ResNet-18 state-dict file (nothing is downloaded)")
    p.add_argument("--keypoints", type=positive_int, default=32, help="spatial soft-argmax keypoints per camera")
    p.add_argument(
        "--hidden",
        type=lambda s: [int(x) for x in csv_list(s)],
        default=[512, 512],
        help="fully connected widths, comma-separated (default: 512,512)",
    )
    p.add_argument(
        "--norm-std-floor",
        type=finite_float,
        default=0.01,
        help="floor of each dimension's normalisation std as a share of its RMS value (default: 0.01)",
    )
    p.add_argument(
        "--norm-clip",
        type=lambda s: None if s.lower() == "none" else positive_float(s),
        default=10.0,
        help="clip normalised inputs to +-this many stds; none: no clipping (default: 10)",
    )
    p.add_argument("--seed", type=non_negative_int, default=0, help="seed of split, shuffles and init (default: 0)")
    p.add_argument(
        "--checkpoint-every", type=positive_int, default=1000, help="steps between checkpoints (default: 1000)"
    )
    p.add_argument("--log-every", type=positive_int, default=100, help="steps between metric lines (default: 100)")
    p.add_argument("--device", default="auto", help="auto, cpu or cuda (default: auto)")
    p.add_argument(
        "--threads", type=positive_int, help="CPU threads for torch (default: torch's; 1 suits busy machines)"
    )
    p.add_argument("--resume", action="store_true", help="continue the run in --output from its last checkpoint")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_bc(args: argparse.Namespace) -> int:
    from shiftkit.policies.bc import BCArgs, train

    if args.regime == "early-stop":
        bound = (
            f"at most {args.steps} steps or {args.max_epochs} epochs"
            if args.steps
            else f"at most {args.max_epochs} epochs"
        )
        print(f"early-stop: {bound}; ends sooner once every member has not improved for {args.patience} epochs")
    metrics = train(
        BCArgs(
            datasets=csv_list(args.dataset),
            output_dir=args.output,
            root=args.root,
            regime=args.regime,
            steps=args.steps,
            max_epochs=args.max_epochs,
            patience=args.patience,
            batch_size=args.batch_size,
            lr=args.lr,
            weight_decay=args.weight_decay,
            val_fraction=args.val_fraction,
            ensemble_size=args.ensemble,
            inputs=args.inputs,
            encoder=args.encoder,
            encoder_weights=args.encoder_weights,
            num_keypoints=args.keypoints,
            hidden=args.hidden,
            norm_std_floor=args.norm_std_floor,
            norm_clip=args.norm_clip,
            seed=args.seed,
            checkpoint_every=args.checkpoint_every,
            log_every=args.log_every,
            device=args.device,
            threads=args.threads,
            resume=args.resume,
        ),
        progress=not args.no_progress,
    )
    shown = ", ".join(
        f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in metrics.items() if not isinstance(v, list)
    )
    print(f"trained BC policy in {args.output}: {shown}")
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="trainer", metavar="TRAINER", required=True)
    bc = sub.add_parser(
        "bc",
        help="behavioural cloning (MSE, ensembles, CNN + spatial soft-argmax)",
        description="Behavioural cloning (SPEC 6.1): MSE action regression by an ensemble.",
    )
    _add_bc_arguments(bc)
    bc.set_defaults(_train_run=_run_bc)
    if importlib.util.find_spec(VPACE_CLI) is not None:
        vpace_cli = importlib.import_module(VPACE_CLI)
        for name, help_text in (
            ("vpace", "VPACE / ACE / SQIL / DAC / RCE from success examples"),
            ("lfgp", "Learning from Guided Play (expert trajectories, per-task DAC)"),
        ):
            p = sub.add_parser(name, help=help_text, description=help_text)
            vpace_cli.add_arguments(p)
            p.set_defaults(_train_run=vpace_cli.run, trainer=name)
        plot = sub.add_parser(
            "plot",
            help="success curves across seeds: IQM with stratified bootstrap 95%% CIs (PNG)",
            description="Plot evaluation success curves of runs: LABEL=RUN[,RUN...] per method.",
        )
        vpace_cli.add_plot_arguments(plot)
        plot.set_defaults(_train_run=vpace_cli.run_plot)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from shiftkit.pipelines.staging import DestinationLock

    if getattr(args, "output", None) is None:  # `train plot` writes no run folder
        return args._train_run(args)
    with DestinationLock(Path(args.output)):  # a second run on the same --output is told who holds it
        return args._train_run(args)
