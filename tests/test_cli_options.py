"""CLI options generated from the config dataclasses, no abbreviations, the trainer registry and a
`shiftkit --help` that imports no torch."""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from dataclasses import dataclass, field
from typing import Any, Literal

import pytest

from shiftkit.app.cli import Parser, build_parser, main
from shiftkit.datasets.dataclass_config import check_fields, option, option_of
from shiftkit.datasets.errors import ConfigError
from shiftkit.datasets.option_values import DataclassOptions


@dataclass
class Example:
    """A config with one field of each kind the generator handles."""

    name: str
    """Required name."""
    count: int = 3
    """How many (a 20% share)."""
    rate: float | None = 0.5
    """Rate, none for off."""
    widths: list[int] = field(default_factory=lambda: [4, 4])
    """Widths."""
    kind: Literal["a", "b"] = "a"
    """Kind."""
    flag: bool = False
    """Switch."""
    extra: dict[str, Any] = field(default_factory=dict)
    """Key-value pairs."""
    shape: tuple[int, ...] = (1, 2)
    """A tuple."""


def _options() -> DataclassOptions:
    return DataclassOptions(Example, rules={"count": "positive_int", "widths": "positive_int"}, flags={"extra": "kv"})


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = Parser(prog="t")
    _options().add_to(parser)
    return parser.parse_args(argv)


def test_generated_options_follow_the_field_types_and_keep_defaults_in_the_dataclass():
    args = _parse(["--name", "x"])
    assert vars(args) == {"name": "x"}  # nothing defaulted by argparse
    assert _options().build(args) == Example(name="x")
    argv = ["--name", "x", "--count", "7", "--rate", "none", "--widths", "8,16", "32", "--kind", "b", "--flag"]
    built = _options().build(_parse([*argv, "--kv", "a=1", "--kv", "b=[2]", "--shape", "3,4"]))
    assert built == Example("x", 7, None, [8, 16, 32], "b", True, {"a": 1, "b": [2]}, (3, 4))
    assert _options().build(_parse(["--name", "x", "--flag", "--no-flag"])).flag is False


def test_help_is_the_field_docstring_with_the_dataclass_default():
    parser = Parser(prog="t")
    _options().add_to(parser)
    text = " ".join(parser.format_help().split())
    assert "--count N How many (a 20% share). (default: 3)" in text
    assert "--widths N [N ...] Widths. (default: 4,4)" in text
    assert "--name NAME Required name. (required)" in text


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--count", "0"], "argument --count: must be a positive integer, got '0'"),
        (["--count", "1.5"], "argument --count: must be a positive integer, got '1.5'"),
        (["--rate", "nan"], "argument --rate: must be a finite number or none, got 'nan'"),
        (["--widths", "4,-1"], "argument --widths: must be a positive integer, got '-1'"),
        (["--kind", "c"], "argument --kind: invalid choice"),
    ],
)
def test_out_of_range_values_are_refused_with_the_rule_message(argv, message, capsys):
    with pytest.raises(SystemExit) as exc:
        _parse(["--name", "x", *argv])
    errors = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(errors) == 1 and message in errors[0], errors


@dataclass
class Inner:
    """A nested config (the base of `Outer.inner`'s type)."""

    size: int = option(3, rule="positive_int")
    """Size."""
    mode: str = option("a", choices=("a", "b"))
    """Mode."""
    sizes: list[int] = option(default_factory=lambda: [1], rule="positive_int")
    """Sizes."""


@dataclass
class OwnInner(Inner):
    """`Inner` with its own default for one field, rule and docstring inherited."""

    size: int = option_of(Inner, "size", 5)


@dataclass
class Outer:
    """A config nesting another."""

    name: str
    """Required name."""
    inner: OwnInner = field(default_factory=lambda: OwnInner(mode="b"))
    """The nested settings."""


def _outer(argv: list[str]) -> tuple[Outer, argparse.ArgumentParser]:
    options = DataclassOptions(Outer, nested={"inner": DataclassOptions(OwnInner, flags={"sizes": "many"})})
    parser = Parser(prog="t")
    options.add_to(parser)
    return options.build(parser.parse_args(["--name", "x", *argv])), parser


def test_a_nested_dataclass_field_gets_dotted_options_in_a_group_of_its_own():
    """`--inner.size` (draccus' spelling, the generator's dashes and flag names), the nested
    default's values as defaults, the rule of the base class's field."""
    built, parser = _outer([])
    assert built == Outer("x") and built.inner == OwnInner(size=5, mode="b")
    built, _ = _outer(["--inner.size", "7", "--inner.many", "2,4"])
    assert built.inner == OwnInner(size=7, mode="b", sizes=[2, 4])  # the options not given keep the nested default
    (group,) = [g for g in parser._action_groups if g.title == "inner options"]
    assert group.description == "The nested settings."
    text = " ".join(parser.format_help().split())
    assert "--inner.size N Size. (default: 5)" in text and "--inner.mode {a,b} Mode. (default: b)" in text
    assert "--inner.many N [N ...] Sizes. (default: 1)" in text
    for argv, message in (
        (["--inner.size", "0"], "argument --inner.size: must be a positive integer, got '0'"),
        (["--inner.many", "2,-1"], "argument --inner.many: must be a positive integer, got '-1'"),
        (["--inner.mode", "c"], "argument --inner.mode: invalid choice"),
    ):
        with pytest.raises(SystemExit) as exc:
            _outer(argv)
        assert exc.value.code == 2, message
    # a nested dataclass built in code is checked with its dotted name
    with pytest.raises(ConfigError, match="inner.size must be a positive integer, got 0"):
        check_fields(Outer("x", OwnInner(size=0)))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--bc.hidden", "64,0"], "argument --bc.hidden: must be a positive integer, got '0'"),
        (["--bc.output-activation", "relu"], "argument --bc.output-activation: invalid choice: 'relu'"),
        (["--bc.ensemble", "0"], "argument --bc.ensemble: must be a positive integer or none, got '0'"),
        (["--bc.val-fraction", "1"], "argument --bc.val-fraction: must be a number in [0, 1) or none, got '1'"),
        (["--hidden", "64"], "unrecognized arguments: --hidden"),
    ],
)
def test_fire_refuses_a_bad_bc_setting_in_one_line(argv, message, capsys):
    base = ["fire", "--dataset", "d", "--env", "panda-play", "--task", "lift", "--output", "o"]
    assert main([*base, *argv]) == 2
    errors = capsys.readouterr().err.strip().splitlines()
    assert len(errors) == 1 and message in errors[0], errors


def test_numeric_choices_are_parsed_before_they_are_compared():
    # `eval --control-hz 5` is the int 5 the env takes, and 7 is refused as no allowed rate
    from shiftkit.app.commands import eval as eval_command

    parser = Parser(prog="eval")
    eval_command.OPTIONS.add_to(parser)
    built = eval_command.OPTIONS.build(parser.parse_args(["--policy", "p", "--task", "lift", "--control-hz", "5"]))
    assert built.control_hz == 5 and built.episodes == 50 and built.env_kwargs == {}
    with pytest.raises(SystemExit):
        parser.parse_args(["--control-hz", "7"])


def test_a_missing_required_option_names_its_flag():
    with pytest.raises(ConfigError, match="required: --name"):
        _options().build(_parse([]))


def _parsers(parser: argparse.ArgumentParser):
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield from _parsers(sub)


def test_no_parser_takes_abbreviations(capsys):
    parsers = list(_parsers(build_parser()))
    assert len(parsers) > 20 and all(not p.allow_abbrev for p in parsers)
    # `--expert` once landed on `--expert-margin` and failed on its type
    for argv, refused in (
        (["fire", "--expert", "local/exp"], "unrecognized arguments: --expert"),
        (["train", "bc", "--data", "x", "--output", "o"], "unrecognized arguments: --data"),
    ):
        assert main(argv) == 2
        errors = capsys.readouterr().err.strip().splitlines()
        assert len(errors) == 1 and refused in errors[0] and "--expert-margin" not in errors[0], errors


def test_fire_options_mirror_every_field_of_its_args(tmp_path):
    from shiftkit.app.commands import fire as fire_command
    from shiftkit.policies.fire.config import FireArgs, FireBC

    options = fire_command._fire_options()
    parser = Parser(prog="fire")
    options.add_to(parser)
    required = ["--dataset", "d", "--env", "panda-play", "--task", "lift", "--output", str(tmp_path)]
    built = options.build(parser.parse_args(required))
    expected = FireArgs(dataset="d", env="panda-play", task="lift", output_dir=str(tmp_path), progress=True)
    assert built == expected
    flags = {a.dest for a in parser._actions}
    fields = {f.name for f in dataclasses.fields(FireArgs)} - {"bc"}
    assert fields | {f"bc.{f.name}" for f in dataclasses.fields(FireBC)} <= flags
    # `--bc.X` is `train bc --X` (same flag names), its values FIRE's
    given = parser.parse_args([*required, "--bc.ensemble", "3", "--bc.keypoints", "8", "--bc.regime", "fixed"])
    assert options.build(given).bc == FireBC(ensemble_size=3, num_keypoints=8, regime="fixed")


def command_paths(parser: argparse.ArgumentParser | None = None, prefix: tuple[str, ...] = ()) -> list[list[str]]:
    """Every command and subcommand of `shiftkit` (walked from the full parser), e.g. ["fire",
    "aggregate"], with [] for `shiftkit` itself."""
    parser = parser or build_parser()
    paths = [list(prefix)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                paths += command_paths(sub, (*prefix, name))
    return paths


def test_the_help_walk_finds_every_command_and_subcommand():
    paths = command_paths()
    from shiftkit.app.commands import COMMANDS
    from shiftkit.policies.trainers import TRAINERS

    assert {p[0] for p in paths if p} == set(COMMANDS.names())
    assert ["fire", "aggregate"] in paths and ["plot", "roc"] in paths and ["import", "robomimic"] in paths
    assert all(["train", name] in paths for name in TRAINERS.names())


def test_every_help_imports_no_torch_or_mujoco():
    """`--help` of every command and subcommand loads neither torch nor MuJoCo (nor lerobot): each in a
    fresh interpreter, all of them at once (a process each, run side by side)."""
    code = (
        "import sys\nfrom shiftkit.app.cli import main\n"
        "assert main(sys.argv[1:]) == 0\n"
        "print(sorted(m for m in ('torch', 'mujoco', 'lerobot') if m in sys.modules))"
    )
    procs = {
        " ".join(path): subprocess.Popen(
            [sys.executable, "-c", code, *path, "--help"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for path in command_paths()
    }
    heavy = {}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=300)
        last = out.strip().splitlines()[-1] if out.strip() else err[-300:]
        if proc.returncode != 0 or last != "[]":
            heavy[name or "shiftkit"] = last
    assert not heavy, heavy


@pytest.mark.parametrize("argv", [["plan", "--stages"], ["plan", "PIPELINE"]])
def test_planning_imports_no_torch_or_mujoco(argv, synthetic_raw, tmp_path):
    """`--help` of the commands, listing the stages and planning a pipeline whose stages need no env
    load neither torch nor MuJoCo (nor lerobot): env families load when a stage asks for one."""
    from tests.test_executors import write_config

    argv = [str(write_config(tmp_path, synthetic_raw, "planned")) if a == "PIPELINE" else a for a in argv]
    code = (
        "import sys\nfrom shiftkit.app.cli import main\n"
        f"assert main({argv!r}) == 0\n"
        "print(sorted(m for m in ('torch', 'mujoco', 'lerobot') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]", out[-500:]


THROWAWAY_INIT = """
import argparse

from shiftkit.datasets.option_values import DataclassOptions
from shiftkit.policies.trainers import Trainer, register

TRAINER = register(Trainer(name="throwaway", help="a trainer made by a test", args=f"{__name__}.args:Args",
    cli=__name__, load_policy="shiftkit.policies.bc_policy:load_policy", citation="Me, 2026."))


def add_arguments(parser: argparse.ArgumentParser, trainer: Trainer) -> None:
    DataclassOptions(trainer.args_class(), flags={"output_dir": "output"}).add_to(parser)


def run(args: argparse.Namespace) -> int:
    return 0
"""

THROWAWAY_ARGS = '''
from dataclasses import dataclass


@dataclass
class Args:
    output_dir: str
    """Where the throwaway run goes."""
    depth: int = 3
    """How deep the throwaway network is."""
'''


def test_trainers_register_themselves_and_a_new_folder_is_found(tmp_path, monkeypatch, capsys):
    """Adding a trainer is one new folder under policies/trainers/: discovery registers it, `train
    --help` lists it and `train NAME` takes the options of the args dataclass in its folder."""
    import shiftkit.policies.trainers as registry
    from shiftkit.policies.trainers import TRAINERS

    assert {"bc", "vpace", "lfgp"} <= set(TRAINERS.names())
    (tmp_path / "throwaway").mkdir()
    (tmp_path / "throwaway" / "__init__.py").write_text(THROWAWAY_INIT)
    (tmp_path / "throwaway" / "args.py").write_text(THROWAWAY_ARGS)
    (tmp_path / "stray.py").write_text("raise AssertionError('a lone module is not a trainer')\n")
    monkeypatch.setattr(registry, "__path__", [*registry.__path__, str(tmp_path)])
    monkeypatch.setattr(TRAINERS, "_discovered", False)
    monkeypatch.setattr(TRAINERS, "_items", dict(TRAINERS._items))
    try:
        found = TRAINERS.get("throwaway")
        assert found.citation == "Me, 2026."
        assert found.args_class().__module__ == "shiftkit.policies.trainers.throwaway.args"
        assert main(["train", "--help"]) == 0
        assert "a trainer made by a test" in capsys.readouterr().out
        assert main(["train", "throwaway", "--help"]) == 0
        assert "How deep the throwaway network is." in capsys.readouterr().out
    finally:
        for name in ("shiftkit.policies.trainers.throwaway", "shiftkit.policies.trainers.throwaway.args"):
            sys.modules.pop(name, None)
    with pytest.raises(ConfigError, match=r"unknown trainer 'nope' \(known: bc, lfgp, throwaway, vpace\)"):
        TRAINERS.get("nope")


THROWAWAY_COMMAND = '''
"""`shiftkit say_hello NAME`: a command made by a test."""

import argparse

HELP = "greet NAME (a command made by a test)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name")


def run(args: argparse.Namespace) -> int:
    print(f"hello {args.name}")
    return 0
'''


def test_a_new_command_module_is_found(tmp_path, monkeypatch, capsys):
    """Adding a command is one new module in `shiftkit.app.commands`: discovery registers it under its
    name (`_` as `-`), `shiftkit --help` lists it and it runs; an unknown command is one line."""
    import shiftkit.app.commands as commands
    from shiftkit.app.commands import COMMANDS

    assert "sim-robot" in COMMANDS and "import" in COMMANDS  # module names sim_robot, import_
    (tmp_path / "say_hello.py").write_text(THROWAWAY_COMMAND)
    monkeypatch.setattr(commands, "__path__", [*commands.__path__, str(tmp_path)])
    monkeypatch.setattr(COMMANDS, "_discovered", False)
    monkeypatch.setattr(COMMANDS, "_items", {})
    try:
        assert main(["--help"]) == 0
        assert "greet NAME (a command made by a test)" in capsys.readouterr().out
        assert main(["say-hello", "world"]) == 0
        assert capsys.readouterr().out == "hello world\n"
    finally:
        sys.modules.pop("shiftkit.app.commands.say_hello", None)
    assert main(["say-goodbye"]) == 2
    assert "invalid choice: 'say-goodbye'" in capsys.readouterr().err


def test_model_cards_cite_the_registered_trainer(tmp_path):
    from shiftkit.policies.run_dir import RunDir
    from shiftkit.policies.trainers import TRAINERS

    run = RunDir(tmp_path / "run", resume=False)
    run.write_config({"trainer": "lfgp", "args": {}, "datasets": []})
    run.write_model_card({"steps": 1})
    assert TRAINERS.get("lfgp").citation in (tmp_path / "run" / "README.md").read_text()
    assert json.loads((tmp_path / "run" / "config.json").read_text())["trainer"] == "lfgp"
