"""Force-matched replay succeeds where position replay fails (thesis §4.4.3), per door task.

As in docs/force_matching.md ("Replay success"): per task of door-tactile, N simulated kinesthetic
demonstrations (seeds SEED..SEED+N-1 for each SEED of `--seeds`, default 100-119: demonstrations
no setting was tuned on), each replayed once by position and once force-matched (calibration
docs/force_matching_calibration.json, `slowdown` 2, `damping_time` 0.25: the settings of
docs/pipelines/force_matched.toml and position_replay.toml) with the `force_match` stage's own code,
through `bench/force_match.py --replay-success`, printed before it runs.

Last line: the JSON result, force-matched minus position replay success in points over every task
and demonstration (thesis: +62.5), with the successes per task and demonstration block and the
Wilson intervals. `--quick`: one demonstration per task.
"""

from __future__ import annotations

from _study import REPO, arguments, bench, pool, report, seeds_of, workspace

TASKS = ("flat-handle-open", "flat-handle-close", "knob-open", "knob-close")
CALIBRATION = REPO / "docs" / "force_matching_calibration.json"


def main() -> None:
    parser = arguments(__doc__, seeds="100")
    parser.add_argument("--demos", type=int, default=20, help="demonstrations per task and seed (default: 20)")
    args = parser.parse_args()
    firsts = [100] if args.quick else seeds_of(args)
    demos = 1 if args.quick else args.demos
    policies: dict[str, list[dict]] = {}
    with workspace(args.workdir) as (_, env):
        for first in firsts:
            result = bench(
                "force_match.py", "--replay-success", str(demos), "--slowdown", "2", "--damping-time", "0.25",
                "--seed", str(first), "--tasks", ",".join(TASKS), "--calibration", str(CALIBRATION), env=env,
            )  # fmt: skip
            for task, counts in result["per_task"].items():
                for mode, label in (("force_matched", "force-matched replay"), ("position", "position replay")):
                    policies.setdefault(label, []).append(
                        {"task": task, "seeds": [first, first + demos - 1], "successes": counts[mode],
                         "episodes": counts["demonstrations"], "teacher_successes": counts["demo_success"]}
                    )  # fmt: skip
    pooled = {name: pool(runs) for name, runs in policies.items()}
    gap = 100 * (pooled["force-matched replay"]["success"] - pooled["position replay"]["success"])
    report(
        "force_match_replay", "force_matched_minus_position_points", gap, args.quick, pooled,
        seeds=firsts, demos_per_task=demos, slowdown=2, damping_time=0.25,
        calibration=str(CALIBRATION.relative_to(REPO)),
    )  # fmt: skip


if __name__ == "__main__":
    main()
