"""`shiftkit view`: a LeRobot dataset as a Rerun recording, shiftkit's own columns included.

lerobot's `lerobot-dataset-viz` draws a fixed set of scalars, one episode per call; this shows what
shiftkit datasets carry beside them, on one timeline `frame` (episode after episode):

* every camera (`world/.../<camera>/rgb`) and depth map (`.../depth`, metres) under its pinhole and
  pose from `meta/cameras.json` (base pose per episode, extrinsics, intrinsics; MuJoCo's camera
  axes: x right, y up, looking along -z), so the 3D view shows where each view was taken from;
* every numeric column as a time series named by its dimension names (`series/<feature>`: state,
  action, wrench, STS displacement, FIRE's discriminator score, ...);
* flags as spans on a state timeline (`flags/<feature>`: `next.success`, `next.done`,
  `intervention`, FIRE's `intervention_request` (the predictor's requests), ...), and labels as
  lanes (`segments/task`, `segments/sts_mode` from the action's `sts_mode` dim, `segments/source`
  of a FIRE dataset: demonstration / policy / expert), the episode index as a lane of its own;
* a multiview dataset's recorded episode and its re-rendered views side by side: the episodes the
  `multiview` stage made from one source episode share their frames on the timeline, each under
  its own view (`world/recorded/...`, `world/view_1/...`, ..., and `series/<view>/...`).

Episodes are read and sent one at a time (columns per episode, `rr.send_columns`); image features
go to Rerun as the PNG bytes the dataset holds.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets.dataset import Dataset
from shiftkit.datasets.depth import is_depth
from shiftkit.datasets.errors import ShiftkitError
from shiftkit.datasets.features import CAMERA_DTYPES, NUMERIC_DTYPES
from shiftkit.datasets.quality import dimension_names

TIMELINE = "frame"
RECORDED = "recorded"
# the action dim a force-matched dataset's policy switches the STS with (transforms/mode_labels.py)
STS_MODE_DIM, STS_MODES = "sts_mode", {0: "visual", 1: "tactile"}
FLAG_COLOR = {"next.success": 0x4CAF50FF, "next.done": 0x9E9E9EFF, "intervention": 0xEF5350FF}
RERUN_MIN = (0, 33)  # StateChange / StateTimelineView


@dataclass
class ViewSummary:
    """What `view_dataset` sent."""

    episodes: int
    frames: int
    entities: list[str]
    views: list[str]


def import_rerun() -> Any:
    """The Rerun SDK, or a one-line error naming the extra that installs it."""
    try:
        import rerun as rr
    except ImportError:
        raise ShiftkitError("the Rerun SDK is not installed: pip install 'shiftkit[viz]' (or rerun-sdk 0.33)") from None
    version = tuple(int(p) for p in rr.__version__.split(".")[:2] if p.isdigit())
    if version < RERUN_MIN:
        raise ShiftkitError(
            f"shiftkit view needs rerun-sdk >= {'.'.join(map(str, RERUN_MIN))} (its state timelines), "
            f"found {rr.__version__}: pip install -U 'shiftkit[viz]'"
        )
    return rr


def episode_views(episode_metas: list[dict[str, Any]]) -> list[list[tuple[int, str]]]:
    """Episodes grouped as they share frames: a recorded episode followed by the views the
    multiview stage re-rendered from it (`meta.multiview.view`: "source" or 0, 1, ...), each
    labelled; any other episode is a group of its own, labelled `recorded`."""
    groups: list[list[tuple[int, str]]] = []
    source_of_group = None
    for i, meta in enumerate(episode_metas):
        mv = meta.get("multiview") if isinstance(meta.get("multiview"), dict) else None
        source = meta.get("source_episode_index")
        if mv is None:
            groups.append([(i, RECORDED)])
            source_of_group = None
            continue
        label = RECORDED if mv.get("view") == "source" else f"view_{int(mv.get('view', 0)) + 1}"
        if groups and source_of_group is not None and source == source_of_group and label != RECORDED:
            groups[-1].append((i, label))
        else:
            groups.append([(i, label)])
            source_of_group = source
    return groups


def _camera_name(key: str) -> str:
    return key.split(".", 2)[-1] if key.count(".") >= 2 else key


def _changes(labels: list[str]) -> tuple[np.ndarray, list[str]]:
    """Frames where a label changes (the first frame included) and the labels from there on."""
    at = [0] + [t for t in range(1, len(labels)) if labels[t] != labels[t - 1]]
    return np.asarray(at, dtype=np.int64), [labels[t] for t in at]


class _Sender:
    """Sends one dataset's episodes to a Rerun recording stream."""

    def __init__(self, rr: Any, rec: Any, features: dict[str, dict[str, Any]], multiview: bool) -> None:
        self.rr, self.rec, self.features, self.multiview = rr, rec, features, multiview
        self.entities: set[str] = set()
        self.static_done: set[str] = set()
        self.source_labels: dict[int, str] | None = None

    def _path(self, root: str, view: str, *rest: str) -> str:
        parts = [root, view, *rest] if self.multiview else [root, *rest]
        return "/".join(parts)

    def _columns(self, path: str, frames: np.ndarray, columns: Any) -> None:
        self.rr.send_columns(
            path, indexes=[self.rr.TimeColumn(TIMELINE, sequence=frames)], columns=columns, recording=self.rec
        )
        self.entities.add(path)

    def _static(self, path: str, archetype: Any) -> None:
        if path not in self.static_done:
            self.rec.log(path, archetype, static=True)
            self.static_done.add(path)

    def _lane(self, path: str, frames: np.ndarray, labels: list[str], config: Any | None = None) -> None:
        at, states = _changes(labels)
        if config is not None:
            self._static(path, config)
        self._columns(path, frames[at], self.rr.StateChange.columns(state=states))

    def episode(self, index: int, view: str, episode: Any, start: int, task_lane: bool) -> None:
        rr = self.rr
        frames_dict = episode.frames
        n = len(episode)
        frames = np.arange(start, start + n, dtype=np.int64)
        if task_lane:
            self._lane("episode", frames, [f"episode {index}"] * n)
        if "task" in frames_dict:
            self._lane(self._path("segments", view, "task"), frames, [str(t) for t in frames_dict["task"]])
        cameras = episode.meta.get("cameras") or {}
        for key, ft in self.features.items():
            values = frames_dict.get(key)
            if values is None:
                continue
            dtype = ft.get("dtype")
            if dtype in CAMERA_DTYPES:
                self._camera(key, ft, view, cameras.get(_camera_name(key), {}), values, frames)
            elif dtype == "bool":
                self._flag(key, view, np.asarray(values).reshape(n, -1).any(axis=1), frames)
            elif dtype in NUMERIC_DTYPES:
                arr = np.asarray(values, dtype=np.float64).reshape(n, -1)
                path = self._path("series", view, key)
                names = dimension_names(ft, arr.shape[1])
                self._static(path, rr.SeriesLines(names=names))
                self._columns(path, frames, rr.Scalars.columns(scalars=arr))
                if key == "action" and STS_MODE_DIM in names:
                    modes = arr[:, names.index(STS_MODE_DIM)]
                    labels = [STS_MODES.get(int(round(m)), f"mode {m:g}") for m in modes]
                    self._lane(self._path("segments", view, STS_MODE_DIM), frames, labels)
                if key == "source":
                    self._lane(self._path("segments", view, "source"), frames, self._source_labels(arr[:, 0]))

    def _source_labels(self, codes: np.ndarray) -> list[str]:
        if self.source_labels is None:
            # FIRE's per-frame source codes (imported only for a dataset that has them: torch)
            from shiftkit.policies.fire.aggregate import SOURCE_DEMO, SOURCE_EXPERT, SOURCE_POLICY

            self.source_labels = {SOURCE_DEMO: "demonstration", SOURCE_POLICY: "policy", SOURCE_EXPERT: "expert"}
        return [self.source_labels.get(int(c), f"source {int(c)}") for c in codes]

    def _flag(self, key: str, view: str, flags: np.ndarray, frames: np.ndarray) -> None:
        config = self.rr.StateConfiguration(
            values=["on", "off"],
            labels=[key, ""],
            colors=[FLAG_COLOR.get(key, 0xFFA726FF), 0x00000000],
            visible=[True, False],
        )
        self._lane(self._path("flags", view, key), frames, ["on" if f else "off" for f in flags], config)

    def _camera(
        self, key: str, ft: dict[str, Any], view: str, camera: dict[str, Any], values: np.ndarray, frames: np.ndarray
    ) -> None:
        rr = self.rr
        name = _camera_name(key)
        base = self._camera_pose(name, view, camera, frames[0])
        n, height, width = values.shape[:3]
        if is_depth(ft):
            fmt = rr.components.ImageFormat(width=width, height=height, channel_datatype="F32")
            columns = rr.DepthImage.columns(
                buffer=np.ascontiguousarray(values, dtype=np.float32).reshape(n, -1).view(np.uint8),  # blobs: bytes
                format=[fmt] * n,
                meter=np.ones(n, dtype=np.float32),
            )
            self._columns(f"{base}/depth", frames, columns)
            return
        from shiftkit.datasets.encoded_frames import source_bytes

        blobs = [source_bytes(f, values) for f in values]
        if all(b is not None for b in blobs):  # the dataset's own PNG bytes
            columns = rr.EncodedImage.columns(blob=blobs, media_type=["image/png"] * n)
        else:  # decoded video frames
            color = "RGB" if values.shape[-1] == 3 else "L"
            fmt = rr.components.ImageFormat(width=width, height=height, color_model=color, channel_datatype="U8")
            columns = rr.Image.columns(buffer=np.ascontiguousarray(values).reshape(n, -1), format=[fmt] * n)
        self._columns(f"{base}/rgb", frames, columns)

    def _camera_pose(self, name: str, view: str, camera: dict[str, Any], start: int) -> str:
        """Logs the episode's base pose, camera extrinsics and pinhole at its first frame; returns the
        camera's entity path."""
        rr = self.rr
        extr, intr, pose = camera.get("extrinsics"), camera.get("intrinsics"), camera.get("base_pose")
        world = self._path("world", view)
        parent = f"{world}/mobile_base" if extr is not None and extr.get("frame") == "base" else world
        path = f"{parent}/{name}"
        at = [rr.TimeColumn(TIMELINE, sequence=[start])]
        if parent.endswith("/mobile_base") and pose is not None:
            yaw = float(pose.get("yaw", 0.0))
            rr.send_columns(
                parent,
                indexes=at,
                columns=rr.Transform3D.columns(
                    translation=[[float(pose.get("x", 0.0)), float(pose.get("y", 0.0)), 0.0]],
                    rotation_axis_angle=[rr.RotationAxisAngle(axis=[0.0, 0.0, 1.0], radians=yaw)],
                ),
                recording=self.rec,
            )
            self.entities.add(parent)
        if extr is not None:
            rr.send_columns(
                path,
                indexes=at,
                columns=rr.Transform3D.columns(
                    translation=[[float(v) for v in extr["position"]]], mat3x3=[np.asarray(extr["rotation"], float)]
                ),
                recording=self.rec,
            )
        if intr is not None:
            self.rec.set_time(TIMELINE, sequence=start)
            self.rec.log(
                path,
                rr.Pinhole(
                    focal_length=[float(intr["fx"]), float(intr["fy"])],
                    principal_point=[float(intr["cx"]), float(intr["cy"])],
                    width=int(intr["width"]),
                    height=int(intr["height"]),
                    camera_xyz=rr.ViewCoordinates.RUB,  # MuJoCo: x right, y up, looking along -z
                    image_plane_distance=0.1,
                ),
            )
        if extr is not None or intr is not None:
            self.entities.add(path)
        return path


def _spawn_viewer(rr: Any, rec: Any) -> None:
    """Starts the Rerun viewer the SDK ships (its `rerun_cli` binary: the `rerun` on PATH is only there
    with the environment's `bin/` on PATH) and connects `rec` to it; a one-line error when it cannot."""
    import importlib.util
    import sys

    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise ShiftkitError(
            "no display for the Rerun viewer (DISPLAY and WAYLAND_DISPLAY are unset): write a recording with "
            "--save FILE.rrd and open it where there is one (or serve it to a browser: `rerun --serve-web FILE.rrd`)"
        )
    spec = importlib.util.find_spec("rerun_cli")
    bundled = Path(spec.origin).parent / "rerun" if spec is not None and spec.origin else None
    try:
        rr.spawn(executable_path=str(bundled) if bundled and bundled.is_file() else None, recording=rec)
    except RuntimeError as exc:
        first = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        raise ShiftkitError(
            f"cannot start the Rerun viewer ({first}): write a recording with --save FILE.rrd and open it "
            "with `rerun FILE.rrd`"
        ) from None


def _blueprint(rr: Any, features: dict[str, dict[str, Any]], views: list[str], multiview: bool, cameras: dict) -> Any:
    import rerun.blueprint as rrb

    def at(root: str, view: str, *rest: str) -> str:
        return "/".join([root, view, *rest] if multiview else [root, *rest])

    camera_rows = []
    for key, ft in features.items():
        if ft.get("dtype") not in CAMERA_DTYPES:
            continue
        name = _camera_name(key)
        leaf = "depth" if is_depth(ft) else "rgb"
        framed = (cameras.get(name) or {}).get("extrinsics", {}).get("frame") == "base"
        row = [
            rrb.Spatial2DView(
                origin=at("world", v, *(["mobile_base"] if framed else []), name, leaf), name=f"{v} {name} {leaf}"
            )
            for v in views
        ]
        camera_rows.append(rrb.Horizontal(*row))
    series = [
        rrb.TimeSeriesView(origin="series", contents=[at("series", v, key) for v in views], name=key)
        for key, ft in features.items()
        if ft.get("dtype") in NUMERIC_DTYPES and ft.get("dtype") != "bool"
    ]
    lanes = rrb.StateTimelineView(
        origin="/", contents=["episode", "flags/**", "segments/**"], name="flags and segments"
    )
    if not camera_rows:  # numbers only: the series beside the lanes
        return rrb.Blueprint(rrb.Horizontal(rrb.Vertical(*series), lanes, column_shares=[3, 2]), collapse_panels=True)
    left = rrb.Vertical(*camera_rows, rrb.Spatial3DView(origin="world", name="camera poses"))
    right = rrb.Vertical(*series, lanes, row_shares=[1] * len(series) + [max(2, len(series) // 2)])
    return rrb.Blueprint(rrb.Horizontal(left, right), collapse_panels=True)


def view_dataset(
    dataset: Dataset, episode: int | None = None, save: str | Path | None = None, progress: bool = True
) -> ViewSummary:
    """Send `dataset` (one episode and its views with `episode`) to Rerun: into the file `save`
    (`.rrd`, written atomically), else to a spawned viewer."""
    from tqdm import tqdm

    from shiftkit.datasets.episode import META_COLUMN

    rr = import_rerun()
    root, reader = dataset.root, dataset.reader
    metas = [
        json.loads(m) if isinstance(m, str) else {}
        for m in (reader.episodes[META_COLUMN] if META_COLUMN in reader.episodes else [None] * reader.num_episodes)
    ]
    groups = episode_views(metas)
    if episode is not None:
        if not 0 <= episode < reader.num_episodes:
            raise ShiftkitError(f"{root}: no episode {episode} (the dataset has {reader.num_episodes})")
        groups = [g for g in groups if any(i == episode for i, _ in g)]
    multiview = any(label != RECORDED for g in groups for _, label in g)
    views = list(dict.fromkeys(label for g in groups for _, label in g))
    features = reader.features

    rec = rr.RecordingStream("shiftkit_view", recording_id=f"shiftkit-view-{Path(root).resolve().name}")
    tmp = None
    if save is not None:
        save = Path(save)
        if save.is_dir():
            raise ShiftkitError(f"--save {save} is a directory; give a .rrd file name")
        if not save.parent.is_dir():
            raise ShiftkitError(f"--save {save}: no such folder {save.parent}")
        tmp = save.with_name(f".{save.name}.tmp-{os.getpid()}")
        rec.save(tmp)
    else:
        _spawn_viewer(rr, rec)
    try:
        rec.send_blueprint(_blueprint(rr, features, views, multiview, reader.cameras.get("cameras", {})))
        sender = _Sender(rr, rec, features, multiview)
        start = frames = sent = 0
        bar = tqdm(total=sum(len(g) for g in groups), desc="view", unit="ep", disable=not progress, leave=False)
        with bar:
            for group in groups:
                length = 0
                for k, (index, label) in enumerate(group):
                    ep = next(iter(reader.iter_episodes([index])))
                    sender.episode(index, label, ep, start, task_lane=k == 0)
                    length = max(length, len(ep))
                    frames += len(ep)
                    sent += 1
                    bar.update(1)
                start += length
        rec.flush()
    except RuntimeError as exc:  # the SDK's: a viewer that went away, a file that cannot be written
        rec.disconnect()
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        first = next((line.strip() for line in str(exc).splitlines() if line.strip()), type(exc).__name__)
        raise ShiftkitError(f"Rerun could not take the recording: {first}") from None
    except BaseException:
        if tmp is not None:
            rec.disconnect()
            tmp.unlink(missing_ok=True)
        raise
    if tmp is not None:
        rec.disconnect()
        os.replace(tmp, save)
    return ViewSummary(sent, frames, sorted(sender.entities), views)


def entity_summary(summary: ViewSummary) -> list[str]:
    """The lines `shiftkit view` prints: what it sent, grouped by kind."""
    kinds: dict[str, list[str]] = {}
    for path in summary.entities:
        kinds.setdefault(path.split("/", 1)[0], []).append(path)
    lines = [f"sent {summary.episodes} episodes, {summary.frames} frames; views: {', '.join(summary.views)}"]
    for kind, paths in kinds.items():
        shown = ", ".join(paths[:6]) + (f", ... ({len(paths)})" if len(paths) > 6 else "")
        lines.append(f"  {kind}: {shown}")
    return lines
