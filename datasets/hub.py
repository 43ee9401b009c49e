"""Push and pull LeRobot datasets and policy checkpoints to a Hugging Face-compatible hub.

Everything goes through the real huggingface_hub client (endpoint from `HF_ENDPOINT`, token from
`HF_TOKEN` or the stored login) and lerobot's own conventions: a dataset push uploads the folder
without `images/`, adds lerobot's dataset card (or the dataset's own `README.md`) and tags the
commit with the codebase version (`v3.0`) that lerobot resolves when it loads a dataset by ID.

Why not `LeRobotDataset.push_to_hub` itself: it pushes the card with `DatasetCard.push_to_hub`,
whose `validate()` POSTs to the fixed public endpoint `https://huggingface.co/api/validate-yaml`
whatever `HF_ENDPOINT` says, so a push to any other (or an offline) hub fails. Here the card is part
of the one commit that also carries the data; `HfApi.create_commit` validates a `README.md` against
the configured endpoint's own `/api/validate-yaml`, and the card is parsed locally first. One commit
also means a failed push never leaves a half-uploaded revision behind the version tag.

A pull downloads into a temporary folder beside the destination and renames it into place only when
complete and checked, so a failed pull writes nothing. Hub failures become one-line `ShiftkitError`s.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import os
import shutil
from collections.abc import Callable, Iterator
from pathlib import Path

from shiftkit.datasets.errors import DatasetError, ShiftkitError
from shiftkit.datasets.ids import find_local_dataset, lerobot_home
from shiftkit.datasets.staging import remove_dead_staging, staging_path

log = logging.getLogger(__name__)

DEFAULT_BRANCH = "main"
# Local bookkeeping that is never part of a pushed repository (huggingface_hub's download metadata,
# git internals) and lerobot's temporary frame images (it pushes without them too).
_NEVER_PUSHED = (".cache", ".git")
_DATASET_SKIPPED = ("images",)
# A dataset push replaces what lives under these folders at the target revision; other files that
# someone added to the repository (docs, extra assets) are left alone.
_DATASET_OWNED = ("data/", "meta/", "videos/")


@dataclasses.dataclass(frozen=True)
class PushResult:
    """What a push made on the hub."""

    repo_id: str
    """The repository pushed to (ORG/NAME)."""
    repo_type: str
    """"dataset" or "model"."""
    branch: str
    """The branch that received the commit."""
    commit: str
    """The commit id now at the head of `branch` (recorded in provenance)."""
    url: str
    """The commit's URL on the hub."""
    tag: str | None
    """The codebase version tag pointing at `commit`, None when the push did not move it."""


def validate_repo_id(repo_id: str) -> None:
    """Raise a one-line ShiftkitError unless `repo_id` is a valid ORG/NAME hub repository id."""
    from huggingface_hub.errors import HFValidationError
    from huggingface_hub.utils import validate_repo_id as hf_validate

    try:
        hf_validate(repo_id)
        # huggingface_hub's pattern takes any Unicode letter, the hub itself ASCII only: checked
        # here, so no command writes a dataset under an id it could never be pushed as.
        valid = repo_id.count("/") == 1 and repo_id.isascii()
    except HFValidationError:
        valid = False
    if not valid:
        raise ShiftkitError(
            f"invalid repo id {repo_id!r}: expected ORG/NAME made of ASCII letters, digits, '-', '_' and '.' "
            "(no '--' or '..', not starting or ending with '-' or '.', at most 96 characters)"
        )


def local_dataset_root(source: str | Path) -> Path:
    """The root of a local LeRobot dataset given as a folder or as an ID under $HF_LEROBOT_HOME."""
    path = find_local_dataset(source)
    if path is not None:
        return path
    folder = Path(source).expanduser()
    if folder.is_dir():
        raise DatasetError(f"{folder}: not a LeRobot dataset (no meta/info.json)")
    raise DatasetError(f"{source}: no such dataset folder, nor a local dataset ID under {lerobot_home()}")


def push_dataset(
    source: str | Path,
    repo_id: str,
    *,
    revision: str | None = None,
    private: bool = False,
    license: str = "apache-2.0",
) -> PushResult:
    """Push a local LeRobot v3.0 dataset (folder or local ID) to `repo_id` on the hub.

    `revision` names the branch to push to (created from main when missing). The codebase version
    tag is moved to the new commit when pushing to main, or to another branch of a repository that
    has no version tag yet, so `pull_dataset(repo_id)` and lerobot both load what was pushed.
    """
    from huggingface_hub.errors import RevisionNotFoundError
    from lerobot.datasets.dataset_metadata import CODEBASE_VERSION
    from lerobot.datasets.utils import DatasetInfo, create_lerobot_dataset_card, get_repo_versions

    validate_repo_id(repo_id)
    root = local_dataset_root(source)
    info = _read_json(root / "meta" / "info.json")
    if info.get("codebase_version") != CODEBASE_VERSION:
        raise DatasetError(
            f"{root}: dataset is LeRobot {info.get('codebase_version')!r}, only {CODEBASE_VERSION} can be pushed "
            "(convert it with lerobot's converter first)"
        )
    own_card = root / "README.md"
    if own_card.is_file():
        card = own_card.read_text(encoding="utf-8")
    else:
        try:  # lerobot's card renders its typed info, which checks the values it needs
            typed = DatasetInfo.from_dict(info)
        except (AttributeError, TypeError, ValueError) as exc:  # e.g. a missing field, features not a mapping
            raise DatasetError(f"{root / 'meta' / 'info.json'}: {_one_line(exc)}") from None
        card = str(create_lerobot_dataset_card(dataset_info=typed, license=license, repo_id=repo_id))
    _check_card(card, own_card)
    branch = revision or DEFAULT_BRANCH

    with _hub_errors(repo_id, branch):
        api = _api()
        result = _push_folder(
            api,
            root,
            repo_id,
            "dataset",
            branch,
            card,
            private,
            skipped=_NEVER_PUSHED + _DATASET_SKIPPED,
            owned=_DATASET_OWNED,
            message=f"Upload LeRobot {CODEBASE_VERSION} dataset with shiftkit",
        )
        if branch == DEFAULT_BRANCH or not get_repo_versions(repo_id):
            with contextlib.suppress(RevisionNotFoundError):
                api.delete_tag(repo_id, tag=CODEBASE_VERSION, repo_type="dataset")
            api.create_tag(repo_id, tag=CODEBASE_VERSION, revision=result.commit, repo_type="dataset")
            result = dataclasses.replace(result, tag=CODEBASE_VERSION)
    return result


def push_checkpoint(
    path: str | Path, repo_id: str, *, revision: str | None = None, private: bool = False
) -> PushResult:
    """Push a policy checkpoint folder to the model repository `repo_id` (its README.md is the card,
    a minimal shiftkit model card otherwise). Files no longer in the folder are removed remotely."""
    folder = Path(path).expanduser()
    if not folder.is_dir() or not any(folder.iterdir()):
        raise ShiftkitError(f"{path}: no such checkpoint folder (or it is empty)")
    validate_repo_id(repo_id)
    own_card = folder / "README.md"
    card = own_card.read_text(encoding="utf-8") if own_card.is_file() else _default_model_card(repo_id)
    _check_card(card, own_card)
    branch = revision or DEFAULT_BRANCH
    with _hub_errors(repo_id, branch):
        return _push_folder(
            _api(),
            folder,
            repo_id,
            "model",
            branch,
            card,
            private,
            skipped=_NEVER_PUSHED,
            owned=("",),
            message="Upload policy checkpoint with shiftkit",
        )


def pull_dataset(
    repo_id: str, revision: str | None = None, root: str | Path | None = None, *, force: bool = False
) -> Path:
    """Download dataset `repo_id` into `root` (default `$HF_LEROBOT_HOME/<repo_id>`).

    Without `revision`, the codebase version lerobot reads (v3.0, or the newest compatible v3.x tag)
    is resolved exactly as lerobot does; a repository without a version tag is an error. A version
    given as `revision` resolves the same way; a branch, tag or commit is taken literally. The
    downloaded `meta/info.json` must declare a compatible codebase version. An existing `root` is
    replaced only with `force`. Returns the dataset root.
    """
    validate_repo_id(repo_id)
    dest = Path(root).expanduser() if root is not None else lerobot_home() / repo_id
    _refuse_existing(dest, force)
    with _hub_errors(repo_id, revision):
        resolved = _dataset_revision(repo_id, revision)
        return _pull(repo_id, "dataset", resolved, dest, check=_check_pulled_dataset)


def pull_checkpoint(
    repo_id: str,
    revision: str | None = None,
    root: str | Path | None = None,
    *,
    force: bool = False,
    check: Callable[[Path], None] | None = None,
) -> Path:
    """Download the model repository `repo_id` at `revision` (default main) into `root`
    (default `$HF_LEROBOT_HOME/checkpoints/<repo_id>`); returns that folder. `check(folder)` sees the
    download before it is put in place (the policies' reader checks that every checkpoint in it is
    data: a refused download leaves nothing behind)."""
    validate_repo_id(repo_id)
    dest = Path(root).expanduser() if root is not None else lerobot_home() / "checkpoints" / repo_id
    _refuse_existing(dest, force)
    revision = revision or DEFAULT_BRANCH
    with _hub_errors(repo_id, revision):
        return _pull(repo_id, "model", revision, dest, check=None if check is None else lambda _, folder: check(folder))


# -- pushing ----------------------------------------------------------------------------------


def _api():
    from huggingface_hub import HfApi

    return HfApi()  # endpoint and token from the environment / stored login, like lerobot's


def _push_folder(
    api,
    folder: Path,
    repo_id: str,
    repo_type: str,
    branch: str,
    card: str,
    private: bool,
    *,
    skipped: tuple[str, ...],
    owned: tuple[str, ...],
    message: str,
) -> PushResult:
    """One commit on `branch` that adds every file of `folder` (but `skipped` top-level entries), the
    card as README.md, and deletes remote files under the `owned` prefixes that are no longer local."""
    from huggingface_hub import CommitOperationAdd, CommitOperationDelete

    api.create_repo(repo_id, repo_type=repo_type, private=private, exist_ok=True)
    if branch != DEFAULT_BRANCH:
        api.create_branch(repo_id, branch=branch, repo_type=repo_type, exist_ok=True)
    files = {
        p.relative_to(folder).as_posix(): p
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.relative_to(folder).parts[0] not in skipped
    }
    operations: list = [
        CommitOperationAdd(path_in_repo=rel, path_or_fileobj=str(p)) for rel, p in files.items() if rel != "README.md"
    ]
    operations.append(CommitOperationAdd(path_in_repo="README.md", path_or_fileobj=card.encode("utf-8")))
    remote = api.list_repo_files(repo_id, repo_type=repo_type, revision=branch)
    operations += [
        CommitOperationDelete(path_in_repo=rel)
        for rel in remote
        if rel not in files and rel not in ("README.md", ".gitattributes") and rel.startswith(owned)
    ]
    info = api.create_commit(
        repo_id, operations=operations, commit_message=message, repo_type=repo_type, revision=branch
    )
    return PushResult(
        repo_id=repo_id, repo_type=repo_type, branch=branch, commit=info.oid, url=info.commit_url, tag=None
    )


def _check_card(card: str, path: Path) -> None:
    """Parse the card's YAML metadata locally (the hub validates it again on commit)."""
    import yaml
    from huggingface_hub import RepoCard

    try:
        RepoCard(card)
    except (ValueError, yaml.YAMLError) as exc:
        where = path if path.is_file() else "generated card"
        raise ShiftkitError(f"{where}: invalid card metadata: {_one_line(exc)}") from None


def _default_model_card(repo_id: str) -> str:
    from huggingface_hub import ModelCardData

    data = ModelCardData(library_name="shiftkit", license="apache-2.0", tags=["robotics", "LeRobot", "shiftkit"])
    return f"---\n{data.to_yaml()}\n---\n\n# {repo_id}\n\nA policy checkpoint trained with shiftkit.\n"


# -- pulling ----------------------------------------------------------------------------------


def _dataset_revision(repo_id: str, revision: str | None) -> str:
    """The revision to download, resolved the way LeRobotDatasetMetadata resolves it."""
    import packaging.version
    from lerobot.datasets.dataset_metadata import CODEBASE_VERSION
    from lerobot.datasets.utils import get_repo_versions, get_safe_version, is_valid_version

    wanted = revision or CODEBASE_VERSION
    if not is_valid_version(wanted):
        return wanted  # a branch, tag name or commit id: taken literally, as lerobot does
    versions = get_repo_versions(repo_id)
    if not versions:
        raise DatasetError(
            f"dataset {repo_id} on the hub has no codebase version tag (lerobot loads {CODEBASE_VERSION}); "
            "push it with `shiftkit push` or pass --revision BRANCH"
        )
    target = packaging.version.parse(wanted)
    if not any(v.major == target.major and v.minor <= target.minor for v in versions):
        found = ", ".join(f"v{v}" for v in sorted(versions))
        raise DatasetError(f"dataset {repo_id} on the hub has versions {found}, none compatible with {wanted}")
    return get_safe_version(repo_id, wanted)


def _check_pulled_dataset(repo_id: str, folder: Path) -> None:
    import packaging.version
    from lerobot.datasets.dataset_metadata import CODEBASE_VERSION

    info_path = folder / "meta" / "info.json"
    if not info_path.is_file():
        raise DatasetError(f"{repo_id}: not a LeRobot dataset (no meta/info.json in the repository)")
    version = str(_read_json(info_path).get("codebase_version"))
    try:
        compatible = packaging.version.parse(version).major == packaging.version.parse(CODEBASE_VERSION).major
    except packaging.version.InvalidVersion:
        compatible = False
    if not compatible:
        raise DatasetError(f"{repo_id}: dataset is LeRobot {version!r}, shiftkit reads {CODEBASE_VERSION}")


def _refuse_existing(dest: Path, force: bool) -> None:
    if dest.exists() and not force:
        raise ShiftkitError(f"{dest} already exists (pass --force to replace it)")


def _pull(repo_id: str, repo_type: str, revision: str, dest: Path, check) -> Path:
    """Download `revision` into a temporary folder beside `dest`, check it, rename it into place."""
    from huggingface_hub import snapshot_download

    commit = _api().repo_info(repo_id, repo_type=repo_type, revision=revision).sha
    with _staging(dest) as staging:
        # Pinned to the commit, so every file comes from the same revision.
        snapshot_download(repo_id, repo_type=repo_type, revision=commit, local_dir=staging)
        # huggingface_hub's download bookkeeping serves only this one-off folder, and lerobot (0.6)
        # takes a `$HF_LEROBOT_HOME/<id>` that holds it for a stale local_dir mirror: it would
        # download the dataset again by ID (or fail offline) instead of loading the pulled copy.
        shutil.rmtree(staging / ".cache", ignore_errors=True)
        if check is not None:
            check(repo_id, staging)
        if dest.exists():  # only with force: swap, then drop the old copy
            old = staging_path(dest, "old")
            old.mkdir()
            os.replace(dest, old / dest.name)
            os.replace(staging, dest)
            shutil.rmtree(old)
        else:
            os.replace(staging, dest)
    log.info("pulled %s %s@%s (commit %s) into %s", repo_type, repo_id, revision, commit, dest)
    return dest


@contextlib.contextmanager
def _staging(dest: Path) -> Iterator[Path]:
    """A temporary folder on dest's filesystem; on failure it and any parents made for it go."""
    made = [p for p in [dest.parent, *dest.parent.parents] if not p.exists()]
    dest.parent.mkdir(parents=True, exist_ok=True)
    remove_dead_staging(dest)
    staging = staging_path(dest, "pull")
    staging.mkdir()
    try:
        yield staging
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        for folder in made:  # innermost first
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


# -- errors -----------------------------------------------------------------------------------


@contextlib.contextmanager
def _hub_errors(repo_id: str, revision: str | None) -> Iterator[None]:
    """Turn huggingface_hub / network failures into one-line ShiftkitErrors naming the problem."""
    import httpx
    from huggingface_hub import constants
    from huggingface_hub.errors import (
        EntryNotFoundError,
        HfHubHTTPError,
        LocalEntryNotFoundError,
        OfflineModeIsEnabled,
        RepositoryNotFoundError,
        RevisionNotFoundError,
    )

    endpoint = constants.ENDPOINT
    offline = f"the hub is switched off (HF_HUB_OFFLINE=1); set HF_HUB_OFFLINE=0 to reach {endpoint}"
    unreachable = f"cannot reach the hub at {endpoint} (check HF_ENDPOINT and the network)"
    try:
        yield
    except OfflineModeIsEnabled:
        raise ShiftkitError(offline) from None
    except LocalEntryNotFoundError as exc:  # a download's wrapper around a network failure
        raise ShiftkitError(offline if isinstance(exc.__cause__, OfflineModeIsEnabled) else unreachable) from None
    except httpx.TransportError:  # connection refused, DNS, timeouts, a broken answer
        raise ShiftkitError(unreachable) from None
    except RevisionNotFoundError:
        raise ShiftkitError(f"revision {revision!r} not found in {repo_id} at {endpoint}") from None
    except HfHubHTTPError as exc:
        status = exc.response.status_code
        server = _one_line(exc.server_message or "")
        if status == 401:  # the hub also answers 401 for private repositories it hides
            message = (
                f"not authorized for {repo_id} at {endpoint} (401): missing or invalid token, or no such "
                "repository (set HF_TOKEN or log in with `hf auth login`)"
            )
        elif status == 403:
            message = f"access to {repo_id} at {endpoint} forbidden (403): {server or 'the token lacks the permission'}"
        elif isinstance(exc, RepositoryNotFoundError):
            message = f"repository {repo_id} not found at {endpoint}"
        elif isinstance(exc, EntryNotFoundError):
            message = f"file not found in {repo_id} at {endpoint}"
        else:
            message = f"hub request for {repo_id} failed at {endpoint} ({status})" + (f": {server}" if server else "")
        raise ShiftkitError(message) from None
    except ValueError as exc:
        # HfApi.create_commit reports the endpoint's card validation failure as a ValueError.
        if str(exc).startswith("Invalid metadata in README.md"):
            raise ShiftkitError(f"the hub at {endpoint} rejected the card of {repo_id}: {_one_line(exc)}") from None
        raise


def _one_line(exc: object) -> str:
    return " ".join(str(exc).split())


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: unreadable JSON ({_one_line(exc)})") from None
