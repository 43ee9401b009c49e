"""What a stage's output must be, checked against its source (not against the stage's own code).

`check_against_source(stage, features, source, outputs)`: every output frame stands for a source
frame (`Episode.source_frames`, non-decreasing); the features the stage carries
(`Stage.carried_features`) hold that frame's values exactly; events (`next.success`, `next.done`,
lerobot's `language_events`) land on the output frame that stands for their frame, or for a dropped
frame on the last output frame before it, never an earlier one, and none is invented; the persistent
language row active at an output frame (lerobot's own `active_at`) is the one active at the frame it
stands for; task segments hold the frames whose source frame they held; camera metadata follows its
feature (carried with it, or describing its new size).

`check_written(root, features, fps, expected)`: a written dataset holds the in-memory outputs (up to
the storage's own rounding: millimetre depth, video coding) and `info.json` declares what the plan
predicted, `info` included.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from shiftkit.datasets.camera_meta import feature_entries
from shiftkit.datasets.depth import depth_unit, is_depth
from shiftkit.datasets.episode import Episode
from shiftkit.datasets.features import CAMERA_DTYPES, Features
from shiftkit.pipelines.frame_map import EVENT_KEYS, LANGUAGE_EVENTS, LANGUAGE_PERSISTENT

# Written by lerobot's video writer from the encoded file, not predicted by a stage.
WRITER_INFO = ("video.", "audio.", "has_audio")


def check_against_source(stage: Any, features: Features, source: Episode, outputs: list[Episode]) -> None:
    """`outputs` (one source episode's, with frame maps) are true to `source` (see the module docstring)."""
    carried = stage.carried_features(features)
    out_features = stage.transform_features(features)
    for out in outputs:
        where = f"{stage.name}: output of source episode {source.meta.get('source_episode_index')}"
        m = out.origin()
        assert len(m) == len(out), f"{where}: frame map of {len(m)} for {len(out)} frames"
        assert len(m) == 0 or (m.min() >= 0 and m.max() < len(source)), f"{where}: frame map outside the source"
        assert np.all(np.diff(m) >= 0), f"{where}: frame map goes back in time"
        for key, src_key in carried.items():
            if key not in out.frames or src_key not in source.frames:
                continue
            if src_key in EVENT_KEYS:
                _check_flags(out.frames[key], source.frames[src_key], m, f"{where} {key!r}")
            elif src_key == LANGUAGE_EVENTS:
                _check_event_rows(list(out.frames[key]), list(source.frames[src_key]), m, f"{where} {key!r}")
            elif src_key == LANGUAGE_PERSISTENT:
                _check_persistent(out, source, key, src_key, m, where)
            else:
                _check_values(out.frames[key], source.frames[src_key], m, f"{where} {key!r}")
        if "task" in carried and source.meta.get("segments") is not None:
            _check_segments(out.meta.get("segments") or [], source.meta["segments"], m, where)
        _check_cameras(out, source, out_features, features, carried, where)


def _check_values(out: np.ndarray, src: np.ndarray, m: np.ndarray, where: str) -> None:
    expected = np.asarray(src)[m]
    got = np.asarray(out)
    if got.dtype == object or expected.dtype == object:
        assert [_plain(v) for v in got] == [_plain(v) for v in expected], f"{where}: values not the source's"
        return
    assert got.dtype == expected.dtype, f"{where}: dtype {got.dtype}, the source's is {expected.dtype}"
    assert got.shape == expected.shape, f"{where}: shape {got.shape}, expected {expected.shape}"
    if not np.array_equal(got, expected, equal_nan=got.dtype.kind == "f"):
        bad = np.flatnonzero(~np.all((got == expected).reshape(len(got), -1), axis=1))
        raise AssertionError(f"{where}: frame {bad[0]} does not hold source frame {m[bad[0]]}'s values")


def as_stored(column: Any) -> list:
    """A language column as the dataset stores it (a persistent row's timestamp in float32)."""

    def row(r: dict) -> dict:
        return {**r, "timestamp": float(np.float32(r["timestamp"]))} if r.get("timestamp") is not None else r

    return [[row(r) for r in (rows or [])] for rows in column]


def _plain(value: Any) -> Any:
    return value.tolist() if isinstance(value, np.ndarray) else value


def owners(m: np.ndarray, n: int) -> list[tuple[int, int]]:
    """(source frame, the output frame its events belong to) for the source frames from the first
    stood-for one to the last: the first output frame standing for it, or for a dropped frame the
    last output frame before it. Written as the rule reads, independently of `frame_map`."""
    pairs = []
    for j in range(int(m[0]), int(m[-1]) + 1):
        standing = np.flatnonzero(m == j)
        pairs.append((j, int(standing[0]) if len(standing) else int(np.flatnonzero(m < j)[-1])))
    return pairs


def _check_flags(out: np.ndarray, src: np.ndarray, m: np.ndarray, where: str) -> None:
    if not len(m):
        return
    got = np.asarray(out).reshape(len(m), -1).astype(bool)
    flags = np.asarray(src).reshape(len(src), -1).astype(bool)
    must = np.zeros_like(got)
    for j, k in owners(m, len(src)):
        must[k] |= flags[j]
    allowed = must.copy()
    allowed[0] |= flags[: m[0]].any(axis=0)  # before the first kept frame: the first may stand for it
    allowed[-1] |= flags[m[-1] + 1 :].any(axis=0)  # after the last: the last may
    lost = np.flatnonzero((must & ~got).any(axis=1))
    assert not len(lost), f"{where}: output frame {lost[0]} lacks the event of the source frames it stands for"
    invented = np.flatnonzero((got & ~allowed).any(axis=1))
    assert not len(invented), f"{where}: output frame {invented[0]} has an event no frame it stands for had"


def _check_event_rows(out: list, src: list, m: np.ndarray, where: str) -> None:
    if not len(m):
        return
    must: list[list] = [[] for _ in m]
    for j, k in owners(m, len(src)):
        must[k] += list(src[j] or [])
    before = [r for j in range(int(m[0])) for r in (src[j] or [])]
    after = [r for j in range(int(m[-1]) + 1, len(src)) for r in (src[j] or [])]
    for k, rows in enumerate(out):
        options = [must[k]]
        if k == 0:
            options += [before + o for o in options]
        if k == len(m) - 1:
            options += [o + after for o in options]
        assert list(rows or []) in options, f"{where}: output frame {k} fires {rows}, expected {must[k]}"


def _check_persistent(out: Episode, source: Episode, key: str, src_key: str, m: np.ndarray, where: str) -> None:
    """lerobot's resolver gives at each output frame the row it gives at the frame it stands for."""
    from lerobot.datasets.language_render import active_at

    out_t, src_t = out.frames["timestamp"], source.frames["timestamp"]
    for k, j in enumerate(m):
        rows, src_rows = list(out.frames[key][k] or []), list(source.frames[src_key][j] or [])
        for style in sorted({r.get("style") for r in src_rows if r.get("style")}):
            ours = active_at(float(out_t[k]), persistent=rows, style=style)
            theirs = active_at(float(src_t[j]), persistent=src_rows, style=style)
            strip = lambda r: None if r is None else {f: v for f, v in r.items() if f != "timestamp"}  # noqa: E731
            assert strip(ours) == strip(theirs), f"{where} {key!r}: frame {k} shows {ours}, source frame {j} {theirs}"


def _segment_at(segments: list[dict], frame: int) -> dict | None:
    for seg in segments:
        if seg["start"] <= frame < seg["end"]:
            return {k: v for k, v in seg.items() if k not in ("start", "end")}
    return None


def _check_segments(out: list[dict], src: list[dict], m: np.ndarray, where: str) -> None:
    for k, j in enumerate(m):
        assert _segment_at(out, k) == _segment_at(src, int(j)), f"{where}: frame {k} is in another segment than {j}"


def _check_cameras(
    out: Episode, source: Episode, out_features: Features, features: Features, carried: dict, where: str
) -> None:
    """A carried camera feature keeps its metadata (under its new name); any other camera feature's
    intrinsics describe its image when the source's did."""
    out_cams, src_cams = out.meta.get("cameras"), source.meta.get("cameras")
    if not src_cams:
        return
    for key, ft in out_features.items():
        if ft["dtype"] not in CAMERA_DTYPES or key not in out.frames:
            continue
        ours = feature_entries(out_cams, key)
        if carried.get(key) in source.frames:
            theirs = feature_entries(src_cams, carried[key])
            assert ours == theirs, f"{where}: {key!r} carries the metadata {ours}, its source feature had {theirs}"
            continue
        if key not in source.frames:
            continue
        intr, src_intr = ours.get("intrinsics"), feature_entries(src_cams, key).get("intrinsics")
        h, w = source.frames[key].shape[1:3]
        if src_intr and (src_intr["width"], src_intr["height"]) == (w, h):
            oh, ow = out.frames[key].shape[1:3]
            assert intr and (intr["width"], intr["height"]) == (ow, oh), (
                f"{where}: intrinsics of {key!r} describe {intr and (intr['width'], intr['height'])}, "
                f"the image is {(ow, oh)}"
            )


# --------------------------------------------------------------------------- written datasets


def check_written(root: Path, features: Features, fps: int, expected: list[Episode]) -> None:
    """The dataset at `root` declares `features` at `fps` exactly (`info` included, but the keys
    lerobot's video writer records from the files, which must describe the written video) and holds
    the episodes `expected` (as read back: depth in metres; video within its coding error)."""
    from shiftkit.datasets.reader import open_lerobot_dataset

    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["fps"] == fps
    written = {
        k: v
        for k, v in info["features"].items()
        if k not in ("timestamp", "frame_index", "episode_index", "index", "task_index")
    }
    assert set(written) == set(features), f"features {sorted(written)}, predicted {sorted(features)}"
    for key, ft in features.items():
        got = written[key]
        assert (got["dtype"], tuple(got["shape"]), got.get("names")) == (
            ft["dtype"],
            tuple(ft["shape"]),
            ft.get("names"),
        ), key
        own = lambda i: {k: v for k, v in (i or {}).items() if not k.startswith(WRITER_INFO)}  # noqa: E731
        assert own(got.get("info")) == own(ft.get("info")), (
            f"{key!r}: info {got.get('info')}, predicted {ft.get('info')}"
        )
        if ft["dtype"] == "video":
            vinfo = got["info"]
            assert (vinfo["video.height"], vinfo["video.width"], vinfo["video.fps"]) == (
                *tuple(ft["shape"])[:2],
                fps,
            ), key
    reader = open_lerobot_dataset(root)
    episodes = list(reader.iter_episodes())
    assert len(episodes) == len(expected)
    for ep, exp in zip(episodes, expected, strict=True):
        assert len(ep) == len(exp)
        np.testing.assert_array_equal(ep.frames["timestamp"], exp.frames["timestamp"].astype(np.float32))
        assert [str(t) for t in ep.frames["task"]] == [str(t) for t in exp.frames["task"]]
        for key, ft in features.items():
            got, want = ep.frames[key], exp.frames[key]
            if ft["dtype"] == "video":
                _close_video(got, want, ft, key)
            elif is_depth(ft) and depth_unit(ft) == "mm":
                assert np.abs(got - want).max() <= 0.0005 + 1e-6, f"{key!r}: more than 0.5 mm off"
            elif np.asarray(want).dtype == object:
                assert as_stored(got) == as_stored(want), key
            else:
                np.testing.assert_array_equal(np.asarray(got).reshape(np.shape(want)), np.asarray(want), err_msg=key)
        assert ep.meta.get("cameras") == exp.meta.get("cameras") or not exp.meta.get("cameras")


def _close_video(got: np.ndarray, want: np.ndarray, ft: dict, key: str) -> None:
    """Video is lossy: RGB within a few grey levels on average; depth within a few of lerobot's 12-bit
    log quantiser steps."""
    if is_depth(ft):
        from shiftkit.datasets.video import depth_quantiser

        lo, hi, shift, _ = depth_quantiser(ft.get("info"))
        step = (float(np.max(want)) + shift) * (np.log(hi + shift) - np.log(lo + shift)) / 4095
        assert np.abs(got - want).max() <= 4 * step + 1e-6, f"{key!r}: depth video off by more than 4 codes"
    else:
        assert np.abs(got.astype(float) - want.astype(float)).mean() <= 12, f"{key!r}: RGB video too far off"
