"""Property-based fuzzing of the readers users feed files to: the raw episode reader, the pipeline
config parser, the LeRobot reader (and `info` / `validate` on it) and every importer (robomimic,
VPACE, ros2, LeRobot v2.1), on mutated files (truncated, garbage, wrong dtypes and shapes,
ragged rows, NaN/inf, wrong JSON values). Every outcome is a clean result or a one-line
ShiftkitError."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.reliability.harness import clean_or_error

RAW_EXAMPLES = 60
CONFIG_EXAMPLES = 60
CONFIG_TEXT_EXAMPLES = 30
LEROBOT_EXAMPLES = 20
# derandomize: the same examples on every run (CI must not depend on luck or on a local example database)
FUZZ = dict(
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)
npy_arrays = st.tuples(
    st.sampled_from(["float32", "float64", "int64", "int32", "bool", "uint8", "complex64", "int16", "<U2"]),
    st.sampled_from([(0,), (1,), (9,), (10,), (11,), (10, 1), (10, 4), (10, 2, 2), (3, 4), ()]),
    st.sampled_from(["zeros", "nan", "inf", "random"]),
)


def _array(spec) -> np.ndarray:
    dtype, shape, fill = spec
    arr = np.zeros(shape, dtype=dtype)
    if arr.dtype.kind in "fc" and arr.size:
        arr.flat[0] = {"zeros": 0.0, "nan": np.nan, "inf": np.inf, "random": 0.5}[fill]
    return arr


mutations = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 0.99)),
    st.tuples(st.just("garbage"), st.binary(max_size=64)),
    st.tuples(st.just("delete"), st.none()),
    st.tuples(st.just("npy"), npy_arrays),
    st.tuples(st.just("json"), st.tuples(st.text(max_size=12), json_values)),
)


def mutate(root: Path, index: int, mutation) -> str:
    """Apply one mutation to the `index`-th file (sorted) under `root`; returns what was done."""
    files = sorted(p for p in root.rglob("*") if p.is_file())
    path = files[index % len(files)]
    kind, arg = mutation
    if kind == "json" and path.suffix != ".json":
        kind, arg = "truncate", 0.5
    if kind == "npy" and path.suffix != ".npy":
        kind, arg = "garbage", b"\x93NUMPY\x01\x00"
    if kind == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * arg)])
    elif kind == "garbage":
        path.write_bytes(arg)
    elif kind == "delete":
        path.unlink()
    elif kind == "npy":
        np.save(path, _array(arg), allow_pickle=False)
    else:
        key, value = arg
        try:
            data = json.loads(path.read_text())
        except (UnicodeDecodeError, json.JSONDecodeError):  # an earlier mutation already broke it
            data = {}
        if isinstance(data, dict):
            key = sorted(data)[len(key) % len(data)] if data and len(key) % 3 else key
            data[key] = value
        else:
            data = value
        path.write_text(json.dumps(data))
    return f"{kind} {path.relative_to(root)}"


def _copy(src: Path) -> tuple[tempfile.TemporaryDirectory, Path]:
    tmp = tempfile.TemporaryDirectory(prefix="shiftkit-fuzz-")
    return tmp, Path(shutil.copytree(src, Path(tmp.name) / src.name))


def _run_sources(source: Path, dest: Path) -> None:
    """What `shiftkit run` does with a source before writing: plan, read and transform every episode."""
    from shiftkit.datasets.sources import SourceConfig
    from shiftkit.pipelines.config import DestinationConfig, PipelineConfig
    from shiftkit.pipelines.planner import plan_pipeline
    from shiftkit.pipelines.work import transform_episode

    plan = plan_pipeline(PipelineConfig([SourceConfig(path=str(source))], DestinationConfig(root=str(dest))))
    for s, src in enumerate(plan.sources):
        for episode in src.iter_episodes(list(range(src.num_episodes))):
            transform_episode(plan, s, episode)


@settings(max_examples=RAW_EXAMPLES, **FUZZ)
@given(
    index=st.integers(0, 10_000), mutation=mutations, second=st.none() | st.tuples(st.integers(0, 10_000), mutations)
)
def test_raw_reader_on_mutated_files(rel_raw, index, mutation, second):
    tmp, root = _copy(rel_raw)
    with tmp:
        mutate(root, index, mutation)
        if second is not None:
            mutate(root, *second)
        clean_or_error(lambda: _run_sources(root, Path(tmp.name) / "out"))


@settings(max_examples=LEROBOT_EXAMPLES, **FUZZ)
@given(index=st.integers(0, 10_000), mutation=mutations)
def test_lerobot_reader_on_mutated_files(rel_ds, index, mutation):
    from shiftkit.datasets.check import validate_dataset
    from shiftkit.datasets.reader import open_lerobot_dataset

    tmp, root = _copy(rel_ds)
    with tmp:
        mutate(root, index, mutation)

        def read() -> None:
            for _ in open_lerobot_dataset(root).iter_episodes():
                pass
            validate_dataset(root)

        clean_or_error(read)


config_fields = st.fixed_dictionaries(
    {},
    optional={
        "seed": json_values,
        "stages": st.lists(
            st.fixed_dictionaries(
                {"name": st.sampled_from(["trim", "subsample", "resample", "filter", "nope", ""]) | json_values},
                optional={
                    "params": st.dictionaries(st.sampled_from(["every", "fps", "head", "x"]), json_values),
                    "version": json_values,
                },
            )
            | json_values,
            max_size=2,
        )
        | json_values,
        "destination": st.fixed_dictionaries(
            {}, optional={"root": json_values | st.just("out"), "repo_id": json_values}
        )
        | json_values,
        "sources": json_values,
        "source": json_values,
        "unknown": json_values,
    },
)


@settings(max_examples=CONFIG_EXAMPLES, **FUZZ)
@given(fields=config_fields)
def test_pipeline_config_parser_on_random_values(rel_raw, tmp_path, fields):
    from shiftkit.pipelines.config import parse_pipeline_config
    from shiftkit.pipelines.planner import plan_pipeline

    data = {"sources": [{"path": str(rel_raw)}], "destination": {"root": "out"}, **fields}

    def parse_and_plan() -> None:
        plan_pipeline(parse_pipeline_config(data, tmp_path, "fuzz.toml"))

    clean_or_error(parse_and_plan)


@settings(max_examples=CONFIG_TEXT_EXAMPLES, **FUZZ)
@given(
    suffix=st.sampled_from([".toml", ".json", ".yaml", ".txt"]), text=st.text(max_size=60), raw=st.binary(max_size=30)
)
def test_pipeline_config_files_with_random_text(tmp_path, suffix, text, raw):
    from shiftkit.pipelines.config import load_pipeline_config

    path = tmp_path / f"p{suffix}"
    path.write_bytes(text.encode("utf-8", "surrogatepass") + raw)
    clean_or_error(lambda: load_pipeline_config(path))


ROBOMIMIC_EXAMPLES = 12


@settings(max_examples=ROBOMIMIC_EXAMPLES, **FUZZ)
@given(
    target=st.sampled_from(["data/demo_0/actions", "data/demo_0/obs/robot0_eef_pos", "data/demo_1/rewards"]),
    array=npy_arrays,
    control_freq=json_values,
    total=st.none() | st.integers(-3, 20) | st.text(max_size=4) | st.floats(allow_nan=True),
)
def test_robomimic_importer_on_mutated_files(tmp_path_factory, target, array, control_freq, total):
    import h5py

    from shiftkit.app.importing import import_dataset
    from tests.test_import_robomimic import _write

    tmp = tmp_path_factory.mktemp("rm")
    path = _write(tmp / "demo.hdf5")
    with h5py.File(path, "a") as f:
        if target in f and _array(array).dtype.kind != "U":
            del f[target]
            f.create_dataset(target, data=_array(array))
        args = json.loads(f["data"].attrs["env_args"])
        args["env_kwargs"]["control_freq"] = control_freq
        f["data"].attrs["env_args"] = json.dumps(args)
        if total is not None:
            f["data"].attrs["total"] = total
    clean_or_error(lambda: import_dataset("robomimic", {"file": str(path)}, "rm/fuzz", tmp / "out"))


VPACE_EXAMPLES = 25
ragged = st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=3), min_size=1, max_size=4)


@settings(max_examples=VPACE_EXAMPLES, **FUZZ)
@given(
    key=st.sampled_from(
        ["observations", "next_observations", "actions", "rewards", "memory_size", "pointer", "count", "dones"]
    ),
    value=st.one_of(st.tuples(st.just("npy"), npy_arrays), st.tuples(st.just("json"), json_values), ragged),
)
def test_vpace_importer_on_mutated_buffers(tmp_path_factory, key, value):
    import gzip
    import pickle

    from shiftkit.app.importing import import_dataset

    tmp = tmp_path_factory.mktemp("vp")
    n = 4
    data = {
        "observations": np.zeros((n, 60), np.float32),
        "next_observations": np.zeros((n, 60), np.float32),
        "actions": np.zeros((n, 4), np.float32),
        "rewards": np.zeros((n, 1), np.float32),
        "dones": np.zeros((n, 1), bool),
        "memory_size": n,
        "pointer": 0,
        "count": n,
    }
    if isinstance(value, tuple) and value[0] == "npy":
        data[key] = _array(value[1])
    else:
        data[key] = value[1] if isinstance(value, tuple) else value
    path = tmp / "3_lift.gz"
    with gzip.open(path, "wb") as f:
        pickle.dump(data, f)
    clean_or_error(lambda: import_dataset("vpace", {"files": [str(path)]}, "vp/fuzz", tmp / "out"))


ROS2_EXAMPLES = 6


@settings(max_examples=ROS2_EXAMPLES, **FUZZ)
@given(
    widths=st.lists(st.integers(0, 4), min_size=1, max_size=3),
    value=st.sampled_from([0.0, np.nan, np.inf, 1e300]),
    field=st.sampled_from(["position", "velocity", "effort"]),
)
def test_ros2_importer_on_joint_vectors_of_changing_width(tmp_path_factory, widths, value, field):
    """Joint vectors whose width changes through the bag (cycling `widths`), holding `value`."""
    from shiftkit.app.importing import import_dataset
    from tests import test_import_ros2 as bags

    tmp = tmp_path_factory.mktemp("ros")
    count = iter(range(10_000))

    def joint_state(t):
        w = widths[next(count) % len(widths)]
        arrays = {"position": np.full(3, 1.0), "velocity": np.zeros(3), "effort": np.zeros(0)}
        arrays[field] = np.full(w, value)
        return bags.TS.types["sensor_msgs/msg/JointState"](header=bags._header(t), name=bags.JOINTS, **arrays)

    typ, period, offset, _ = bags.STREAMS["/joint_states"]
    streams = {**bags.STREAMS, "/joint_states": (typ, period, offset, joint_state)}
    bag = bags._write_bag(tmp / "bag", duration_ns=300_000_000, streams=streams)
    mapping = tmp / "m.toml"
    camera = '[features."observation.images.front"]\ntopic = "/camera/image_raw"\n'  # not what is fuzzed here
    mapping.write_text(bags.MAPPING.replace('field = "position"', f'field = "{field}"').replace(camera, ""))
    options = {"bags": [str(bag)], "mapping": str(mapping)}
    clean_or_error(lambda: import_dataset("ros2", options, "ros/fuzz", tmp / "out"))


V21_EXAMPLES = 8


@settings(max_examples=V21_EXAMPLES, **FUZZ)
@given(
    target=st.sampled_from(["meta/info.json", "meta/episodes.jsonl", "meta/tasks.jsonl", "meta/episodes_stats.jsonl"]),
    key=st.sampled_from(
        ["fps", "features", "total_chunks", "video_path", "episode_index", "tasks", "length", "task", "stats"]
    ),
    value=json_values,
)
def test_lerobot_v21_importer_on_mutated_metadata(tmp_path_factory, target, key, value):
    from shiftkit.app.importing import import_dataset
    from tests.test_import_lerobot_v21 import _write_v21

    tmp = tmp_path_factory.mktemp("v21")
    src = _write_v21(tmp / "src")
    path = src / target
    if path.suffix == ".json":
        info = json.loads(path.read_text())
        info[key] = value
        path.write_text(json.dumps(info))
    else:
        lines = [json.loads(line) for line in path.read_text().splitlines()]
        lines[-1][key] = value
        path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    clean_or_error(lambda: import_dataset("lerobot-v2.1", {"source": str(src)}, "v21/fuzz", tmp / "out"))


INFO_VALIDATE_EXAMPLES = 12


@settings(max_examples=INFO_VALIDATE_EXAMPLES, **FUZZ)
@given(index=st.integers(0, 10_000), mutation=mutations, command=st.sampled_from(["info", "validate"]))
def test_info_and_validate_on_mutated_datasets(rel_ds, index, mutation, command):
    """`shiftkit info` / `validate` on a mutated dataset: a result or one line with exit 2."""
    from tests.reliability.harness import cli

    tmp, root = _copy(rel_ds)
    with tmp:
        mutate(root, index, mutation)
        outcome = cli([command, str(root)])
        assert outcome.clean, outcome


LOADER_EXAMPLES = 40


def _loaders():
    from shiftkit.datasets import loaders
    from shiftkit.policies.fire.runs import EPISODE_LINE

    return {
        "info": loaders.load_info,
        "stats": loaders.load_stats,
        "provenance": loaders.load_provenance,
        "run config": loaders.load_run_config,
        "evaluation": loaders.load_evaluation,
        "card": lambda p: loaders.load_json_object(p, "card metrics"),
        "metrics": loaders.load_metrics,
        "fire metrics": lambda p: loaders.load_metrics(p, EPISODE_LINE, split="episode"),
    }


# A valid file of each loader's kind, that the fuzz mutates one value of (or replaces whole).
_VALID = {
    "info": {"fps": 10, "features": {"action": {"dtype": "float32", "shape": [4], "names": None}}, "total_frames": 3},
    "stats": {"action": {"mean": [0.0, 1.0], "std": [1.0, 1.0]}},
    "provenance": {"sources": [{"kind": "raw", "env": "panda-play"}], "stages": [{"name": "trim", "report": {"a": 1}}]},
    "run config": {"trainer": "bc", "args": {"steps": 2}, "datasets": [{"id": "me/x", "root": "/d", "fps": 10}]},
    "evaluation": {"env": "e", "task": "t", "seed": 0, "episodes": 2, "success_rate": 0.5, "ci95": [0.1, 0.9]},
    "card": {"val_loss": 0.1},
    "metrics": {"step": 1, "split": "train", "loss": 0.5},
    "fire metrics": {
        **{"step": 1, "split": "episode", "d_ready": True, "policy_success": False},
        **{"expert_samples": 3, "execution_time_s": 1.0, "scores": {"beta": 1.0, "gda": 0.5, "doubt": 0.0}},
    },
}


def _set_path(doc, path: list[str], value):
    """`doc` with the value at `path` (keys of nested objects, the last one set or added) replaced."""
    if not path or not isinstance(doc, dict):
        return value
    key, rest = path[0], path[1:]
    return {**doc, key: _set_path(doc.get(key), rest, value) if rest else value}


@settings(max_examples=LOADER_EXAMPLES, **FUZZ)
@given(
    kind=st.sampled_from(sorted(_VALID)),
    where=st.lists(
        st.sampled_from(
            [
                "fps",
                "features",
                "action",
                "shape",
                "mean",
                "sources",
                "stages",
                "report",
                "args",
                "datasets",
                "ci95",
                "step",
                "split",
                "scores",
                "beta",
                "env",
                "x",
            ]
        ),
        min_size=0,
        max_size=3,
    ),  # fmt: skip
    value=json_values | st.sampled_from([float("nan"), float("inf"), 1e308, -1, True, "", [], {}]),
    garbage=st.none() | st.binary(max_size=24),
)
def test_every_loader_on_random_values(tmp_path_factory, kind, where, value, garbage):
    """Each typed loader on its valid file with a random value at a random place (or the whole file
    random bytes): the value it returns has the types its schema promises, or one line."""
    path = tmp_path_factory.mktemp("loader") / ("metrics.jsonl" if "metrics" in kind else "file.json")
    doc = _set_path(_VALID[kind], where, value)
    if garbage is not None:
        path.write_bytes(garbage)
    else:
        path.write_text(json.dumps(doc))
    clean_or_error(lambda: _loaders()[kind](path))


@settings(max_examples=LOADER_EXAMPLES // 2, **FUZZ)
@given(array=npy_arrays, cut=st.none() | st.floats(0, 0.99))
def test_array_loader_on_random_arrays(tmp_path_factory, array, cut):
    """`load_array` on arrays of any dtype and shape, NaN/inf, truncated: an array or one line."""
    from shiftkit.datasets.loaders import load_array

    path = tmp_path_factory.mktemp("npy") / "a.npy"
    np.save(path, _array(array), allow_pickle=False)
    if cut is not None:
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * cut)])
    clean_or_error(lambda: load_array(path, "an array", ndim=(1, 2)))


@settings(max_examples=LOADER_EXAMPLES // 2, **FUZZ)
@given(value=json_values, as_tuple=st.booleans(), key=st.integers(-3, 3) | st.text(max_size=4))
def test_data_tree_round_trips_and_refuses_garbage(tmp_path_factory, value, as_tuple, key):
    """The pickle-free store of checkpoints and parts gives the same tree back (tuples, integer keys,
    arrays), and a random document in its place is one line."""
    from shiftkit.datasets import data_tree

    tree = {"v": (value, np.arange(3, dtype=np.int16)) if as_tuple else value, "k": {key: np.float32(1.5)}}
    path = tmp_path_factory.mktemp("tree") / "t.tree"
    with open(path, "wb") as f:
        data_tree.save_tree(f, tree)
    back = data_tree.load_tree(path)
    assert repr(back) == repr(tree)
    good = path.read_bytes()
    header = json.dumps(value).encode()
    with open(path, "wb") as f:  # a random document as the header
        f.write(data_tree.MAGIC + len(header).to_bytes(8, "little") + header)
    clean_or_error(lambda: data_tree.load_tree(path))
    path.write_bytes(good[: len(good) // 2])  # cut short
    clean_or_error(lambda: data_tree.load_tree(path))
