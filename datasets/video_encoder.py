"""Which encoder settings an encoded RGB video camera gets: the destination's where given
(`[destination]` `vcodec`, `pix_fmt`, `g`, `crf`, `preset`: lerobot 0.6.1's `VideoEncoderConfig`
names), else those its source recorded in the feature's `info` (`video.codec`, `video.pix_fmt`,
`video.g`, `video.crf`, ...), else lerobot's defaults; and whether a source stream already is what
the destination asks for (then it can still be copied). Depth keeps lerobot's depth encoder: its
12-bit codes need a codec and pixel format that hold them (docs/video_depth.md)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
from collections.abc import Iterator
from typing import Any

from shiftkit.datasets.errors import ConfigError, DatasetError
from shiftkit.datasets.video import check_frame_size, resolve, scheduling_kept

ENCODER_SETTINGS = ("vcodec", "pix_fmt", "g", "crf", "preset")
"""The encoder settings a destination may give, by lerobot's `VideoEncoderConfig` field names."""

# What belongs to one encoder and means nothing (or something else) to another: not carried from a
# source encoded with another codec than the destination's.
_CODEC_SPECIFIC = ("preset", "fast_decode", "extra_options")
# x264's and x265's crf range: their FFmpeg option accepts more and the encoder clamps it silently.
_CRF_MAX = {"h264": 51, "hevc": 51}


def rgb_encoder(info: dict[str, Any] | None, settings: dict[str, Any]) -> Any:
    """lerobot's `RGBEncoderConfig` for a camera whose feature `info` is `info`, with the given
    `settings` (a subset of `ENCODER_SETTINGS`) over the source's recorded ones. ValueError (lerobot's
    own check against this machine's FFmpeg: codec, pixel format, option ranges) when they cannot
    encode here."""
    from lerobot.configs import RGBEncoderConfig
    from lerobot.configs.video import VIDEO_CODECS_ALIASES, encoder_config_from_video_info

    base = encoder_config_from_video_info(info) if "video.codec" in (info or {}) else RGBEncoderConfig()
    if not settings:
        return base
    changes = dict(settings)
    vcodec = settings.get("vcodec", base.vcodec)
    if (
        VIDEO_CODECS_ALIASES.get(vcodec, vcodec) != base.vcodec
    ):  # another encoder: its own defaults for what is specific to one
        defaults = {f.name: f for f in dataclasses.fields(RGBEncoderConfig)}
        for name in _CODEC_SPECIFIC:
            if name not in changes:
                field = defaults[name]
                changes[name] = (
                    field.default_factory() if field.default_factory is not dataclasses.MISSING else field.default
                )
    return dataclasses.replace(base, **changes)


def encoded_info(info: dict[str, Any] | None, settings: dict[str, Any]) -> dict[str, Any]:
    """A camera's feature `info` with the encoder settings it is encoded with (`rgb_encoder`) as its
    `video.*` keys, which the writer reads back (lerobot's `encoder_config_from_video_info`), then
    overwrites with what it probes from the written stream. Resolved once (`video.resolve`): a worker
    takes its main process's answer."""

    def compute() -> dict[str, Any]:
        from lerobot.configs.video import VIDEO_ENCODER_INFO_FIELD_NAMES

        config = rgb_encoder(info, settings)
        recorded = {"video.codec": config.vcodec, "video.pix_fmt": config.pix_fmt}
        return recorded | {f"video.{name}": getattr(config, name) for name in sorted(VIDEO_ENCODER_INFO_FIELD_NAMES)}

    return {**(info or {}), **resolve("encoded_info", compute, info, settings)}


def check_rgb_encoder(key: str, feature: dict[str, Any], settings: dict[str, Any]) -> None:
    """ConfigError, in one line, when camera `key` (its `feature`) cannot be encoded with the
    destination's `settings`: lerobot's checks, a crf past the codec's range, and what only the encoder
    itself refuses when it opens (a preset it does not know)."""
    import av

    if not settings:
        return
    given = ", ".join(f"{k} = {v!r}" for k, v in settings.items())
    try:
        config = rgb_encoder(feature.get("info"), settings)
        height, width = tuple(feature["shape"])[:2]
        check_frame_size(config.vcodec, height, width)  # before the encoder opens: it would crash
        _open_encoder(config, height, width)
    except (ValueError, av.error.FFmpegError, DatasetError) as exc:
        reason = " ".join(str(exc).split())
        raise ConfigError(f"[destination] {given}: cannot encode {key} on this machine: {reason}") from None


def _open_encoder(config: Any, height: int, width: int) -> None:
    """Open (and close) the encoder `config` describes for frames of this size, as lerobot's
    `encode_video_frames` sets it up; what it refuses raises."""
    from fractions import Fraction

    import av

    codec = _codec_name(config.vcodec)
    if codec in _CRF_MAX and config.crf is not None and not 0 <= config.crf <= _CRF_MAX[codec]:
        raise ValueError(f"crf {config.crf} is out of {config.vcodec}'s range 0-{_CRF_MAX[codec]}")
    ctx = av.CodecContext.create(config.vcodec, "w")
    ctx.width, ctx.height, ctx.pix_fmt, ctx.time_base = width, height, config.pix_fmt, Fraction(1, 30)
    ctx.options = config.get_codec_options(as_strings=True)
    # its refusal goes into the error, not to stderr: FFmpeg's log and the encoder library's own
    # (x264 prints an unknown preset there itself)
    with _stderr_silenced(), scheduling_kept():
        try:
            ctx.open()
        except av.error.FFmpegError as exc:
            raise ValueError(f"the {ctx.codec.name} encoder refuses these settings ({exc.strerror})") from None


@contextlib.contextmanager
def _stderr_silenced() -> Iterator[None]:
    """File descriptor 2 to /dev/null while the block runs (what C libraries print goes nowhere)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def stream_matches(info: dict[str, Any] | None, settings: dict[str, Any]) -> bool:
    """Whether the source stream recorded in `info` is what every given setting asks for (codec by
    the stream's codec name, as lerobot records it: "libsvtav1" and "av1" alike), so that copying it
    gives what encoding would; a setting the source did not record is taken as different."""
    info = info or {}
    for name, wanted in settings.items():
        recorded = info.get("video.codec" if name == "vcodec" else f"video.{name}")
        if name == "vcodec":
            recorded, wanted = _codec_name(recorded), _codec_name(wanted)
        if recorded is None or recorded != wanted:
            return False
    return True


def _codec_name(encoder: str | None) -> str | None:
    """The codec an encoder (or a stream codec name) writes, as PyAV names a stream's codec."""
    import av
    from lerobot.configs.video import VIDEO_CODECS_ALIASES

    if encoder is None:
        return None
    try:
        return av.codec.Codec(VIDEO_CODECS_ALIASES.get(encoder, encoder), "w").canonical_name
    except ValueError:  # no encoder by that name: a stream's codec name
        return encoder
