"""The counts behind the README's "Reliability" section, computed from the suite itself.

`python -m tests.reliability.counts` prints the section; `test_counts.py` checks the README holds
exactly this text, so the numbers cannot drift from the tests that back them.
"""

from __future__ import annotations

import inspect


def _tests(module) -> list[str]:
    return [name for name, obj in inspect.getmembers(module, inspect.isfunction) if name.startswith("test_")]


def counts() -> dict[str, int]:
    from tests.reliability import test_cli_errors, test_data_not_code, test_faults, test_fuzz, test_integrity

    fuzz = (
        test_fuzz.RAW_EXAMPLES
        + test_fuzz.LEROBOT_EXAMPLES
        + test_fuzz.CONFIG_EXAMPLES
        + test_fuzz.CONFIG_TEXT_EXAMPLES
        + test_fuzz.ROBOMIMIC_EXAMPLES
        + test_fuzz.VPACE_EXAMPLES
        + test_fuzz.ROS2_EXAMPLES
        + test_fuzz.V21_EXAMPLES
        + test_fuzz.INFO_VALIDATE_EXAMPLES
        + test_fuzz.LOADER_EXAMPLES
        + 2 * (test_fuzz.LOADER_EXAMPLES // 2)
    )
    # tampered checkpoints and work parts: the CLI cases, last.txt naming a path outside, a part
    # holding a pickle, a pulled checkpoint with a payload
    tampered = len(test_data_not_code.CASES) + 3
    # SIGKILLs at seeded random points, plus one fault per other fault test (the README lists them).
    faults = len(test_faults.KILL_SEEDS) + len(_tests(test_faults)) - 1
    integrity = len(_tests(test_integrity)) - 2 + test_integrity.EVENT_EXAMPLES  # minus the two meta tests
    return {
        "bad_inputs": len(test_cli_errors.CASES) + len(test_cli_errors.OS_ERRORS) + tampered,
        "fuzzed": fuzz,
        "faults": faults,
        "integrity": integrity,
    }


def readme_section() -> str:
    c = counts()
    return f"""## Reliability

`tests/reliability/` keeps shiftkit honest under bad input and faults, and runs with the other tests:

* {c["bad_inputs"]} bad inputs against the CLI (negative seeds, invalid repo ids, malformed raw and
  LeRobot metadata, metadata files of the right syntax but the wrong types (an info.json that is a
  list, provenance, statistics, run configs and FIRE metrics with missing or non-numeric fields,
  robomimic datasets where groups belong), malformed importer files and plan arrays, 16-bit images,
  non-UTF-8 paths, env arguments out of range, unwritable or file-blocked outputs, two outputs at one
  path, an output inside an input and one input given twice (by path or as a copy), checkpoints
  that carry a pickled payload, ...): each ends in a correct result or one line
  `shiftkit COMMAND: error: ...` with exit 2, no input is modified and no payload runs.
* {c["fuzzed"]} fuzzed files and configs (hypothesis: truncated files, garbage, wrong dtypes and
  shapes, ragged rows, NaN/inf, random JSON values) for the raw episode reader, the LeRobot
  reader and `info` / `validate` on it, the pipeline config parser and every importer
  (robomimic, VPACE, ros2, LeRobot v2.1), every typed loader of `datasets/loaders.py` and the
  pickle-free store of checkpoints and work parts: a clean result or a one-line error, never
  another exception.
* {c["faults"]} faults injected: SIGKILL of `shiftkit run` at seeded random points (the resumed run
  writes the clean run's bytes and no pool worker outlives its parent), SIGKILL of a Ray run (every
  process of its Ray cluster exits), a second run on the same destination (and a second trainer
  on one `--output`), a trainer refused early (no folder left), a stale lock, a full disk, a run
  that can never resume, a killed writer's staging folder (a SIGKILLed `import lerobot-v2.1`'s
  among them; the next writer of any command removes it), a writer beaten to its destination, a
  250-character destination name, a reader that closes stdout early, and an evaluation of an
  unfinished training run.
* {c["integrity"]} checks against silent wrong results: stale parts after the source changed,
  success flags kept by every frame-rate-changing stage (property-based), statistics that no longer
  match the data (`shiftkit validate --deep`), dataset ids that do not match, example sets, VPACE
  buffer pointers and the provenance of `collect --lerobot`.

The counts are computed by `python -m tests.reliability.counts`, and a test keeps this section equal
to its output.
"""


if __name__ == "__main__":
    print(readme_section(), end="")
