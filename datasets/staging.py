"""Staging folders: what a writer fills beside its destination before one rename puts it in place.

Every command that writes a folder (a LeRobot or raw dataset, `collect`, `import`, `pull`) writes
it first into `.<name>.<kind>-<pid>-<hex>` next to the destination. The pid names the owner, so a
later writer into the same destination can tell the leftovers of a killed (or beaten) writer
from a folder another process is still filling, and removes only the former. A destination name
too long to take the suffix within the file system's name limit is replaced by a hash of it, so
a legal destination never fails on shiftkit's own temporary name (nor on its work folder's).
"""

from __future__ import annotations

import contextlib
import errno
import glob
import hashlib
import os
import shutil
import uuid
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from shiftkit.datasets.errors import ConfigError, DatasetError, ShiftkitError

_NAME_MAX = 255  # bytes per path component on Linux/macOS file systems
_SUFFIX_BYTES = 48  # room for ".<kind>-<pid>-<hex>" or ".<suffix>" of every sibling shiftkit names


def _stem(target: Path) -> str:
    name = target.name
    if len(os.fsencode(name)) + 1 + _SUFFIX_BYTES <= _NAME_MAX:
        return name
    return "h" + hashlib.sha256(os.fsencode(name)).hexdigest()[:32]


def sibling(target: str | Path, suffix: str) -> Path:
    """The hidden path `.<name>.<suffix>` beside `target` (a work folder, a lock)."""
    target = Path(target)
    return target.parent / f".{_stem(target)}.{suffix}"


def require_writable(folder: str | Path, flag: str) -> None:
    """The nearest existing folder on the way to `folder` must take new files (tried, not guessed), so
    a command refuses an unwritable output before minutes of work rather than after them."""
    import tempfile

    folder = Path(folder).absolute()
    existing = next(p for p in [folder, *folder.parents] if p.exists())
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise ConfigError(f"{flag}: cannot write into {existing} ({exc.strerror})") from None


def check_inputs_and_outputs(
    inputs: Sequence[tuple[str, str | Path]],
    outputs: Sequence[tuple[str, str | Path]] = (),
    content_key: Callable[[Path], str | None] | None = None,
) -> None:
    """The one rule of every command that writes: an output is never an input, inside one or around
    one (a run into its own source, a recording over its plan), and no input is given twice, by
    resolved path (`ds` and `./ds/`, a symlink) or by `content_key` (e.g. a dataset's fingerprint: a
    copy of the same dataset). `inputs` and `outputs` are (what the user called it, path) pairs; a
    ConfigError names both in one line."""
    resolved = [(f"{label} {path}", Path(path).expanduser().resolve()) for label, path in inputs]
    for label, path in outputs:
        out = Path(path).expanduser().resolve()
        for shown, source in resolved:
            if out == source or out.is_relative_to(source):
                raise ConfigError(f"{label} {path} lies inside the input {shown}; choose an output outside it")
            if source.is_relative_to(out):
                raise ConfigError(f"{label} {path} holds the input {shown}; choose an output that does not")
    seen: dict[Path, str] = {}
    keys: dict[str, str] = {}
    for shown, source in resolved:
        if source in seen:
            raise ConfigError(f"{shown} is {seen[source]} again ({source}): give each input once")
        seen[source] = shown
        key = content_key(source) if content_key is not None and source.exists() else None
        if key is not None and key in keys:
            raise ConfigError(f"{shown} holds the same data as {keys[key]} (a copy): give each input once")
        if key is not None:
            keys[key] = shown


def staging_path(target: str | Path, kind: str = "partial") -> Path:
    """A fresh, not yet created staging path for `target` owned by this process."""
    return sibling(target, f"{kind}-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def remove_dead_staging(target: str | Path) -> None:
    """Remove the staging folders of `target` (any kind) whose owning process no longer runs."""
    target = Path(target)
    if not target.parent.is_dir():
        return
    prefix = f".{_stem(target)}."
    for path in target.parent.glob(glob.escape(prefix) + "*"):
        _, _, owner = path.name[len(prefix) :].partition("-")
        pid, _, rest = owner.partition("-")
        if pid.isdigit() and rest and not _alive(int(pid)):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    path.unlink()


def publish(staging: Path, target: Path) -> None:
    """Rename the filled `staging` folder onto `target`; when another writer got there first (or
    the rename fails otherwise) the staging folder goes and the error is one line."""
    try:
        if target.exists() or target.is_symlink():
            raise FileExistsError
        os.rename(staging, target)
    except OSError as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(exc, FileExistsError) or exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
            raise DatasetError(f"destination already exists: {target} (another run wrote it meanwhile)") from None
        raise DatasetError(f"cannot move the finished output into {target}: {exc.strerror}") from None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


class DestinationLock:
    """An exclusive lock on a destination (`.<name>.shiftkit-work.lock` beside it, flock'ed, holding
    the owner's pid), held by every command that writes there over a while (`run`, the trainers).

    The kernel drops the flock when its owner dies, so the lock of a killed run is simply taken
    over; a second live run on the same destination gets a one-line error naming the first."""

    def __init__(self, destination: Path) -> None:
        self.path = sibling(destination, "shiftkit-work.lock")
        self._fd: int | None = None
        self._made: list[Path] = []

    def __enter__(self) -> DestinationLock:
        import fcntl

        parent = self.path.parent
        self._made = [p for p in [parent, *parent.parents] if not p.exists()]  # removed again if left empty
        parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                owner = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                raise ShiftkitError(
                    f"another shiftkit run (pid {owner}) is writing this destination (lock {self.path}); "
                    "wait for it to finish or stop it"
                ) from None
            # The file may have been removed by the previous owner between open and flock.
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._fd is not None:
            self.path.unlink(missing_ok=True)
            os.close(self._fd)
            self._fd = None
            for folder in self._made:  # innermost first; a command that failed early leaves no folders
                try:
                    folder.rmdir()
                except OSError:
                    break
