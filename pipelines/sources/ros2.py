"""Import ROS 2 recordings (rosbag2 directories, .mcap or .db3 files) as LeRobot datasets.

Bags are read with `rosbags`' AnyReader, which deserialises every message with the type
definitions the bag embeds (a current ROS 2 type store is the fallback for bags without them).
A mapping file (TOML, YAML or JSON) says which topic fields become which feature:

    fps = 10
    align = "hold-last"          # or "nearest"
    task = "pick up the cube"
    [[features."observation.state"]]
    topic = "/joint_states"
    field = "position"
    [features."observation.images.front"]
    topic = "/camera/image_raw"  # sensor_msgs/Image or CompressedImage
    [[features.action]]
    topic = "/cmd_vel"
    field = "linear.x"

Time alignment: frames are sampled every 1/fps s from the moment every mapped topic has published
(the latest first message) to the moment the first topic stops (the earliest last message), on the
bag's receive timestamps (or the messages' header stamps with `time = "header"`). `hold-last` takes each topic's latest message at or before the frame time
(what a controller running at that instant had seen); `nearest` the message closest in time
(ties: the earlier). One bag is one episode, or, with `split_topic`, every message on that topic
starts a new episode (frames before the first one are dropped).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from shiftkit.pipelines.episode import Episode
from shiftkit.pipelines.errors import ConfigError, DatasetError
from shiftkit.pipelines.features import Features, image_feature, vector_feature
from shiftkit.pipelines.sources import Importer, ImportSummary, write_imported

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}


@dataclass
class TopicField:
    """One topic field feeding (part of) a feature."""

    topic: str
    """The ROS topic, e.g. /joint_states."""
    field: str | None = None
    """Dotted path into the message (`position`, `linear.x`, `data`); omitted for camera features."""
    indices: list[int] | None = None
    """Keep only these elements of an array field (default: all)."""
    names: list[str] | None = None
    """One name per kept dimension (default: JointState-style `name` entries, else `<topic>.<field>_<i>`)."""


@dataclass
class Ros2Mapping:
    """The mapping file of `shiftkit import ros2`."""

    features: dict[str, TopicField | list[TopicField]]
    """Feature name -> the topic field(s) it is made of, concatenated in order.
    `observation.images.<name>` features take one image topic."""
    fps: int | None = None
    """Frame rate of the dataset (`--fps` overrides)."""
    align: Literal["nearest", "hold-last"] = "hold-last"
    """How a topic's messages are sampled at the frame times (see the module docs)."""
    task: str | None = None
    """Task text of every frame (`--task` overrides)."""
    split_topic: str | None = None
    """Every message on this topic starts a new episode (default: one bag, one episode)."""
    robot_type: str | None = None
    """Robot type recorded in the dataset's info."""
    time: Literal["receive", "header"] = "receive"
    """Message times: the bag's receive timestamps, or each message's `header.stamp` (sensor time)."""
    sources: dict[str, list[TopicField]] = field(init=False)

    def __post_init__(self) -> None:
        self.sources = {k: v if isinstance(v, list) else [v] for k, v in self.features.items()}
        if not self.sources:
            raise ValueError("map at least one feature")
        if self.fps is not None and self.fps < 1:
            raise ValueError(f"fps must be a positive integer, got {self.fps}")
        for key, parts in self.sources.items():
            if not parts:
                raise ValueError(f"feature {key!r} maps no topic")
            if key.startswith("observation.images.") and (len(parts) != 1 or parts[0].field is not None):
                raise ValueError(f"camera feature {key!r} takes exactly one image topic and no field")

    def topics(self) -> list[str]:
        """The topics the mapping reads, each once, in order of first use."""
        names = [p.topic for parts in self.sources.values() for p in parts]
        return list(dict.fromkeys(names))


def load_mapping(path: str | Path) -> Ros2Mapping:
    """The `Ros2Mapping` in a .toml, .yaml or .json mapping file."""
    from shiftkit.pipelines.config import read_config_file
    from shiftkit.pipelines.dataclass_config import from_dict

    return from_dict(Ros2Mapping, read_config_file(path, "mapping file"), str(path))


def _resolve(msg: Any, path: str, where: str) -> Any:
    value = msg
    for i, part in enumerate(path.split(".")):
        if not hasattr(value, part):
            fields = [f for f in getattr(value, "__dataclass_fields__", {}) if not f.startswith("_")]
            done = ".".join(path.split(".")[:i]) or "the message"
            raise DatasetError(f"{where}: {done} ({type(value).__name__}) has no field {part!r} (fields: {fields})")
        value = getattr(value, part)
    return value


def _vector(msg: Any, part: TopicField, where: str) -> np.ndarray:
    value = _resolve(msg, part.field, where)
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: field {part.field!r} is not numeric ({type(value).__name__})") from None
    if part.indices is not None:
        if any(not -len(arr) <= i < len(arr) for i in part.indices):
            raise DatasetError(f"{where}: indices {part.indices} out of range for {part.field!r} ({len(arr)} values)")
        arr = arr[part.indices]
    return arr


def _default_names(msg: Any, part: TopicField, width: int) -> list[str]:
    leaf = part.field.rsplit(".", 1)[-1]
    joint_names = getattr(msg, "name", None)  # sensor_msgs/JointState: name[i] labels position[i], ...
    if isinstance(joint_names, list) and len(joint_names) >= width and part.field in ("position", "velocity", "effort"):
        picked = [joint_names[i] for i in part.indices] if part.indices is not None else joint_names[:width]
        return [f"{n}.{leaf}" for n in picked]
    topic = part.topic.strip("/").replace("/", ".")
    if width == 1 and part.indices is None and not isinstance(_resolve(msg, part.field, ""), (list, np.ndarray)):
        return [f"{topic}.{part.field}"]
    return [f"{topic}.{part.field}_{i}" for i in (part.indices if part.indices is not None else range(width))]


def _image(msg: Any, where: str) -> np.ndarray:
    """RGB uint8 (H, W, 3) from sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8) or CompressedImage."""
    if hasattr(msg, "encoding"):
        channels = _CHANNELS.get(msg.encoding)
        if channels is None:
            raise DatasetError(f"{where}: image encoding {msg.encoding!r} is not supported ({', '.join(_CHANNELS)})")
        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        data = np.asarray(msg.data, dtype=np.uint8)
        if step < w * channels or data.size < h * step:
            raise DatasetError(f"{where}: image data ({data.size} bytes) does not fit {h}x{w} {msg.encoding}")
        img = data[: h * step].reshape(h, step)[:, : w * channels].reshape(h, w, channels)
        if msg.encoding.startswith("bgr"):
            img = img[..., [2, 1, 0]]
        elif msg.encoding == "mono8":
            img = np.repeat(img, 3, axis=2)
        return np.ascontiguousarray(img[..., :3])
    import cv2

    img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise DatasetError(f"{where}: compressed image ({msg.format!r}) cannot be decoded")
    return np.ascontiguousarray(img[..., ::-1])


def _sample(times: np.ndarray, frame_times: np.ndarray, align: str) -> np.ndarray:
    """Index of the message each frame takes (`times` sorted, every frame time within [times[0], times[-1]])."""
    after = np.searchsorted(times, frame_times, side="right")  # first message later than the frame
    last = after - 1  # latest message at or before the frame
    if align == "hold-last":
        return last
    nxt = np.minimum(after, len(times) - 1)
    return np.where(times[nxt] - frame_times < frame_times - times[last], nxt, last)


@contextmanager
def _reading(path: Path) -> Iterator[None]:
    """Turns the readers' errors on a missing or corrupt bag into one-line DatasetErrors."""
    from rosbags.highlevel import AnyReaderError

    try:
        yield
    except DatasetError:
        raise
    except (AnyReaderError, FileNotFoundError, OSError) as exc:
        raise DatasetError(f"{path}: cannot read the bag ({' '.join(str(exc).split())})") from None
    except Exception as exc:  # rosbags' storage readers raise their own classes (ReaderError, sqlite3, mcap)
        raise DatasetError(
            f"{path}: cannot read the bag ({type(exc).__name__}: {' '.join(str(exc).split())})"
        ) from None


@contextmanager
def _messages(path: Path, topics: list[str]) -> Iterator[tuple[Any, Iterator[tuple[Any, int, bytes]]]]:
    """The reader and the (connection, receive time ns, raw bytes) of `topics`, in the bag's order."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with _reading(path), AnyReader([path], default_typestore=get_typestore(Stores.LATEST)) as reader:
        known = {c.topic: c.msgtype for c in reader.connections}
        missing = [t for t in topics if t not in known]
        if missing:
            raise DatasetError(f"{path}: no topic {missing[0]!r} in the bag (topics: {sorted(known)})")
        yield reader, reader.messages(connections=[c for c in reader.connections if c.topic in topics])


@dataclass
class _BagIndex:
    """Pass 1 over a bag: per mapped topic its message times, sorted, and each one's index in bag order."""

    times: dict[str, np.ndarray]
    order: dict[str, np.ndarray]
    markers: list[int]
    types: dict[str, str]


def _scan(path: Path, mapping: Ros2Mapping) -> _BagIndex:
    """Message times only (messages are deserialised just for their header stamps with time = "header")."""
    wanted = mapping.topics() + ([mapping.split_topic] if mapping.split_topic else [])
    times: dict[str, list[int]] = {t: [] for t in mapping.topics()}
    markers: list[int] = []
    types: dict[str, str] = {}
    with _messages(path, wanted) as (reader, stream):
        for connection, timestamp, raw in stream:
            types[connection.topic] = connection.msgtype
            if mapping.time == "header":
                msg = reader.deserialize(raw, connection.msgtype)
                timestamp = _header_time(msg, timestamp, connection, path, required=connection.topic in times)
            if connection.topic == mapping.split_topic:
                markers.append(timestamp)
            if connection.topic in times:
                times[connection.topic].append(timestamp)
    for topic, ts in times.items():
        if not ts:
            raise DatasetError(f"{path}: topic {topic!r} has no messages")
    order = {t: np.argsort(np.asarray(ts, dtype=np.int64), kind="stable") for t, ts in times.items()}
    return _BagIndex(
        {t: np.asarray(ts, dtype=np.int64)[order[t]] for t, ts in times.items()}, order, sorted(markers), types
    )


def _header_time(msg: Any, receive_ns: int, connection: Any, path: Path, required: bool) -> int:
    """`header.stamp` in ns; a split marker without a header keeps its receive time."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is None:
        if required:
            raise DatasetError(
                f'{path}: {connection.topic} ({connection.msgtype}) has no header.stamp; use time = "receive"'
            )
        return receive_ns
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


@dataclass
class _Plan:
    """One episode of a bag: its frame window and the message (bag-order index) each topic gives each frame."""

    segment: int
    start: int
    picks: dict[str, np.ndarray]


def _plan(path: Path, mapping: Ros2Mapping, index: _BagIndex, fps: int) -> list[_Plan]:
    if mapping.split_topic is not None and not index.markers:
        raise DatasetError(f"{path}: split topic {mapping.split_topic!r} has no messages")
    ends = [2**63 - 1]
    bounds = (
        list(zip(index.markers, [*index.markers[1:], *ends], strict=True)) if mapping.split_topic else [(-1, *ends)]
    )
    plans = []
    for segment, (seg_start, seg_end) in enumerate(bounds):
        inside = {t: np.flatnonzero((ts >= seg_start) & (ts < seg_end)) for t, ts in index.times.items()}
        if any(len(i) == 0 for i in inside.values()):
            continue  # a topic is silent in this segment: no frame can be built
        start = max(int(index.times[t][i[0]]) for t, i in inside.items())
        end = min(int(index.times[t][i[-1]]) for t, i in inside.items())
        if end < start:
            continue
        n = (end - start) * fps // 1_000_000_000 + 1
        frame_times = start + (np.arange(n, dtype=np.int64) * 1_000_000_000) // fps
        picks = {
            t: index.order[t][i[_sample(index.times[t][i], frame_times, mapping.align)]] for t, i in inside.items()
        }
        plans.append(_Plan(segment, start, picks))
    if not plans:
        raise DatasetError(f"{path}: the mapped topics never publish together; no frame can be built")
    return plans


def _fetch(path: Path, mapping: Ros2Mapping, plans: list[_Plan]) -> dict[str, dict[int, Any]]:
    """Pass 2: deserialise only the messages some frame takes (a 30 Hz camera sampled at 10 fps keeps a
    third of its images), so memory holds one bag's output frames, not the bag."""
    wanted = mapping.topics() + ([mapping.split_topic] if mapping.split_topic else [])  # same stream as pass 1
    needed = {t: {int(k) for plan in plans for k in plan.picks[t]} for t in mapping.topics()}
    fetched: dict[str, dict[int, Any]] = {t: {} for t in needed}
    seen = dict.fromkeys(needed, 0)
    with _messages(path, wanted) as (reader, stream):
        for connection, _, raw in stream:
            topic = connection.topic
            if topic not in needed:
                continue
            if seen[topic] in needed[topic]:
                fetched[topic][seen[topic]] = reader.deserialize(raw, connection.msgtype)
            seen[topic] += 1
    return fetched


def _schema(path: Path, mapping: Ros2Mapping, types: dict[str, str], first: dict[str, Any]) -> Features:
    """Features from the first message each topic contributes."""
    features: Features = {}
    for key, parts in mapping.sources.items():
        if key.startswith("observation.images."):
            topic = parts[0].topic
            if types[topic] not in IMAGE_TYPES:
                raise DatasetError(
                    f"{path}: camera feature {key!r} maps {topic!r} of type {types[topic]}, not an image"
                )
            features[key] = image_feature(_image(first[topic], f"{path} {topic}").shape)
            continue
        names: list[str] = []
        for part in parts:
            where = f"{path} {part.topic} ({types[part.topic]})"
            if part.field is None:
                raise DatasetError(f"mapping: feature {key!r} needs a 'field' for topic {part.topic!r}")
            width = len(_vector(first[part.topic], part, where))
            if part.names is not None and len(part.names) != width:
                raise DatasetError(
                    f"mapping: {key!r} gives {len(part.names)} names for {width} values of {part.field!r}"
                )
            names += part.names or _default_names(first[part.topic], part, width)
        if len(set(names)) != len(names):
            raise DatasetError(f"mapping: feature {key!r} has repeated dimension names {names}; give 'names'")
        features[key] = vector_feature("float32", names)
    return features


def _episode(
    path: Path,
    mapping: Ros2Mapping,
    plan: _Plan,
    messages: dict[str, dict[int, Any]],
    features: Features,
    fps: int,
    task: str,
) -> Episode:
    frames: dict[str, np.ndarray] = {}
    for key, parts in mapping.sources.items():
        if key.startswith("observation.images."):
            topic = parts[0].topic
            imgs = [_image(messages[topic][int(k)], f"{path} {topic}") for k in plan.picks[topic]]
            if any(img.shape != tuple(features[key]["shape"]) for img in imgs):
                raise DatasetError(f"{path}: images on {topic!r} differ in size from the first bag's")
            frames[key] = np.stack(imgs)
            continue
        columns = []
        for part in parts:
            msgs = messages[part.topic]
            vectors = [_vector(msgs[int(k)], part, f"{path} {part.topic}") for k in plan.picks[part.topic]]
            odd = next((i for i, v in enumerate(vectors) if len(v) != len(vectors[0])), None)
            if odd is not None:
                raise DatasetError(
                    f"{path} {part.topic}: field {part.field!r} changes width mid-bag ({len(vectors[0])} values, "
                    f"then {len(vectors[odd])} at frame {odd} of the episode starting at {plan.start} ns)"
                )
            columns.append(np.stack(vectors))
        try:
            value = np.concatenate(columns, axis=1)
        except ValueError:
            raise DatasetError(f"{path}: {key!r} changes width between messages") from None
        if value.shape[1] != features[key]["shape"][0]:
            raise DatasetError(
                f"{path}: {key!r} has {value.shape[1]} values, the first bag had {features[key]['shape'][0]}"
            )
        if not np.isfinite(value).all():
            raise DatasetError(f"{path}: {key!r} has NaN/inf values")
        frames[key] = value.astype(np.float32)
    n = len(next(iter(plan.picks.values())))
    frames["timestamp"] = np.arange(n, dtype=np.float64) / fps
    frames["task"] = np.array([task] * n)
    source = {"bag": path.name, "start_ns": plan.start, "segment": plan.segment}
    return Episode(frames, {"task": task, "source": source})


def _fingerprint(path: Path) -> str:
    digest = hashlib.sha256()
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        digest.update(str(file.relative_to(path) if path.is_dir() else file.name).encode())
        with file.open("rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


def import_ros2(
    bags: list[str | Path],
    mapping_path: str | Path,
    repo_id: str,
    root: str | Path,
    fps: int | None = None,
    align: str | None = None,
    task: str | None = None,
) -> ImportSummary:
    """Write the bags (one episode each, or split) into one new LeRobot dataset at `root`."""
    from shiftkit.pipelines.hub import validate_repo_id

    validate_repo_id(repo_id)
    if not bags:
        raise DatasetError("no bags given")
    mapping = load_mapping(mapping_path)
    fps = fps or mapping.fps
    if fps is None or fps < 1:
        raise ConfigError(f"{mapping_path}: give a positive fps (in the mapping file or --fps), got {fps}")
    if align is not None:
        mapping.align = align
    task = task or mapping.task
    if not task:
        raise ConfigError(f"{mapping_path}: give the task (in the mapping file or --task)")
    paths = [Path(b) for b in bags]
    # the first bag fixes the schema (widths, image sizes) before anything is written
    index = _scan(paths[0], mapping)
    plans = _plan(paths[0], mapping, index, fps)
    messages = _fetch(paths[0], mapping, plans)
    first = {t: messages[t][int(plans[0].picks[t][0])] for t in mapping.topics()}
    features = _schema(paths[0], mapping, index.types, first)
    per_file: list[dict[str, Any]] = []

    def episodes():
        nonlocal plans, messages
        for i, path in enumerate(paths):
            if i > 0:
                plans = _plan(path, mapping, _scan(path, mapping), fps)
                messages = _fetch(path, mapping, plans)
            eps = [_episode(path, mapping, plan, messages, features, fps, task) for plan in plans]
            per_file.append({"file": path.name, "episodes": len(eps), "lengths": [len(e) for e in eps]})
            yield from eps

    num_episodes, num_frames = write_imported(
        repo_id,
        root,
        fps,
        features,
        episodes(),
        robot_type=mapping.robot_type,
        sources=[{"kind": "ros2", "path": str(p.resolve()), "sha256": _fingerprint(p)} for p in paths],
        importer={
            "name": "ros2",
            "fps": fps,
            "align": mapping.align,
            "split_topic": mapping.split_topic,
            "time": mapping.time,
            "features": {k: [vars(p) for p in v] for k, v in mapping.sources.items()},
        },
    )
    return ImportSummary(Path(root), mapping.align, fps, num_episodes, num_frames, per_file)


def _add_arguments(parser) -> None:
    parser.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 directories or .mcap/.db3 files")
    parser.add_argument("--mapping", required=True, help="mapping file (TOML/YAML/JSON): topic fields -> features")
    parser.add_argument("--fps", type=int, help="frame rate (default: the mapping file's)")
    parser.add_argument("--align", choices=("nearest", "hold-last"), help="time alignment (default: the mapping's)")
    parser.add_argument("--task", help="task text (default: the mapping file's)")


def _report(summary: ImportSummary) -> list[str]:
    return [f"{f['file']}: {f['episodes']} episode(s), lengths {f['lengths']}" for f in summary.per_file]


IMPORTER = Importer(
    name="ros2",
    help="ROS 2 bags / MCAP through rosbags, with a mapping file from topic fields to features",
    add_arguments=_add_arguments,
    run=lambda args: import_ros2(
        args.bags, args.mapping, args.repo_id, args.root, fps=args.fps, align=args.align, task=args.task
    ),
    report=_report,
)
