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

from shiftkit.datasets.dataclass_config import check_fields, from_dict, option, read_config_file
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.features import Features, image_feature, vector_feature
from shiftkit.datasets.importers import Importer, register_importer
from shiftkit.datasets.sources import groups_by_file

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
    fps: int | None = option(None, rule="positive_int")
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
        check_fields(self)
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


@dataclass
class Ros2Options:
    """Options of the ROS 2 importer (`shiftkit import ros2 BAG... --mapping FILE`)."""

    bags: list[str]
    """rosbag2 directories or .mcap/.db3 files (one episode each, or split)."""
    mapping: str
    """Mapping file (TOML/YAML/JSON): topic fields -> features."""
    fps: int | None = option(None, rule="positive_int")
    """Frame rate (default: the mapping file's)."""
    align: Literal["nearest", "hold-last"] | None = None
    """Time alignment (default: the mapping's)."""
    task: str | None = None
    """Task text (default: the mapping file's)."""


class Ros2Source:
    """ROS 2 bags as a pipeline source: one group per bag. Opening it scans every bag's message times
    and plans each episode's frames; a bag's messages are deserialised when its episodes are read."""

    def __init__(self, options: Ros2Options) -> None:
        if not options.bags:
            raise DatasetError("no bags given")
        mapping = self.mapping = load_mapping(options.mapping)
        fps = options.fps or mapping.fps
        if fps is None or fps < 1:
            raise ConfigError(f"{options.mapping}: give a positive fps (in the mapping file or --fps), got {fps}")
        if options.align is not None:
            mapping.align = options.align
        self.task = options.task or mapping.task
        if not self.task:
            raise ConfigError(f"{options.mapping}: give the task (in the mapping file or --task)")
        self.fps, self.robot_type = fps, mapping.robot_type
        self.inputs = [Path(b) for b in options.bags]
        self._plans: list[list[_Plan]] = []
        self._cached: tuple[int, dict[str, dict[int, Any]]] | None = None  # the last bag's fetched messages
        types: dict[str, str] = {}
        for b, path in enumerate(self.inputs):
            index = _scan(path, mapping)
            self._plans.append(_plan(path, mapping, index, fps))
            if b == 0:  # the first bag fixes the schema (widths, image sizes)
                types = index.types
        first_plan = self._plans[0][0]
        messages = self._messages(0)
        first = {t: messages[t][int(first_plan.picks[t][0])] for t in mapping.topics()}
        self.features = _schema(self.inputs[0], mapping, types, first)
        self._episodes = [(b, k) for b, plans in enumerate(self._plans) for k in range(len(plans))]
        self.num_episodes = len(self._episodes)

    def _messages(self, bag: int) -> dict[str, dict[int, Any]]:
        if self._cached is None or self._cached[0] != bag:
            self._cached = (bag, _fetch(self.inputs[bag], self.mapping, self._plans[bag]))
        return self._cached[1]

    def episode_groups(self) -> list[list[int]]:
        """The episodes of each bag."""
        return groups_by_file([b for b, _ in self._episodes])

    def iter_episodes(self, indices: list[int]) -> Iterator[Episode]:
        """The episodes at `indices`, in that order."""
        for i in indices:
            b, k = self._episodes[i]
            plan = self._plans[b][k]
            path = self.inputs[b]
            episode = _episode(path, self.mapping, plan, self._messages(b), self.features, self.fps, self.task)
            episode.meta["source_episode_index"] = i
            yield episode

    def describe(self) -> dict[str, Any]:
        """The provenance entry: the bags (with fingerprints and episode lengths) and the mapping."""
        mapping = self.mapping
        return {
            "kind": "ros2",
            "bags": [
                {
                    "path": str(path.resolve()),
                    "sha256": _fingerprint(path),
                    "lengths": [len(next(iter(p.picks.values()))) for p in plans],
                }
                for path, plans in zip(self.inputs, self._plans, strict=True)
            ],
            "importer": {
                "name": "ros2",
                "fps": self.fps,
                "align": mapping.align,
                "split_topic": mapping.split_topic,
                "time": mapping.time,
                "features": {k: [vars(p) for p in v] for k, v in mapping.sources.items()},
            },
        }


def _report(source: dict[str, Any]) -> list[str]:
    return [
        f"{Path(bag['path']).name}: {len(bag['lengths'])} episode(s), lengths {bag['lengths']}"
        for bag in source["bags"]
    ]


IMPORTER = register_importer(
    Importer(
        name="ros2",
        help="ROS 2 bags / MCAP through rosbags, with a mapping file from topic fields to features",
        Options=Ros2Options,
        inputs=("bags", "mapping"),
        open=Ros2Source,
        report=_report,
    )
)
