"""Start-up of the `shiftkit` command line: `shiftkit --help` wall time vs `python -c pass`.

Both run as fresh processes of this interpreter, interleaved round by round (so machine load
affects both alike); the medians are compared. `shiftkit train --help`, `shiftkit fire --help` and
`shiftkit plan --stages` are timed beside it, and each command's imports are checked for torch and
mujoco, which none of them needs (only the command named on the command line builds its options,
and env families load when a stage asks for one).

    python bench/cli_startup.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

COMMANDS = {
    "help": ["-m", "shiftkit.app.cli", "--help"],
    "train_help": ["-m", "shiftkit.app.cli", "train", "--help"],
    "fire_help": ["-m", "shiftkit.app.cli", "fire", "--help"],
    "plan_stages": ["-m", "shiftkit.app.cli", "plan", "--stages"],
    "pass": ["-c", "pass"],
}
HEAVY = ("torch", "mujoco")


def _wall(argv: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, *argv], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def _heavy_imports(argv: list[str]) -> list[str]:
    """The heavy modules a CLI invocation imports (from `python -X importtime`)."""
    done = subprocess.run([sys.executable, "-X", "importtime", *argv], capture_output=True, text=True, check=True)
    names = {line.rsplit("|", 1)[-1].strip().split(".")[0] for line in done.stderr.splitlines() if "|" in line}
    return sorted(n for n in HEAVY if n in names)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--quick", action="store_true", help="5 rounds instead of 20")
    args = parser.parse_args()
    rounds = 5 if args.quick else 20
    times: dict[str, list[float]] = {name: [] for name in COMMANDS}
    for _ in range(rounds):
        for name, argv in COMMANDS.items():
            times[name].append(_wall(argv))
    median = {name: statistics.median(t) for name, t in times.items()}
    result = {
        "bench": "cli_startup",
        "metric": "help_vs_python_startup",
        "value": round(median["help"] / median["pass"], 2),
        "goal": 3.0,
        "higher_is_better": False,
        **{f"{name}_s": round(m, 3) for name, m in median.items()},
        "heavy_imports": {name: _heavy_imports(argv) for name, argv in COMMANDS.items() if name != "pass"},
        "rounds": rounds,
        "load_1min": round(os.getloadavg()[0], 1),
        "quick": args.quick,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
