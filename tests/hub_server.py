"""A loopback Hugging Face Hub for tests: the HTTP routes that huggingface_hub and lerobot call to
push and pull a repository, served on 127.0.0.1 from a repository store on disk.

It is a test double for the remote service only; the client side under test is the real
huggingface_hub / lerobot code. Implemented (as the public Hub answers them, JSON bodies and the
`X-Error-Code` / `X-Error-Message` headers the client maps to its exceptions):

* `POST /api/repos/create` (`visibility` "public"/"private", or the older `private` flag),
  `POST /api/validate-yaml`
* `GET /api/{type}s/{repo}[/revision/{rev}]`, `GET .../refs`, `GET .../tree/{rev}[/{path}]`
* `POST .../preupload/{rev}` (always answers `regular`: no LFS/xet), `POST .../commit/{rev}` (NDJSON)
* `POST .../branch/{name}`, `POST .../tag/{rev}`, `DELETE .../tag/{name}`
* `HEAD|GET /[datasets/]{repo}/resolve/{rev}/{path}`

Store layout: `<root>/<type>s/<org>/<name>/repo.json` (privacy, branches, tags),
`commits/<oid>.json` (parent, message, full tree `{path: blob oid}`) and `blobs/<git sha1>`.
Auth: `tokens` maps a bearer token to "read" or "write"; an unknown token is a 401, writing
without a token a 401, writing with a read token a 403, reading a private repo without a valid
token a 401 (the Hub hides private repos). Every write token may write every namespace.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import re
import threading
from datetime import UTC, datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

import yaml

REPO_TYPES = ("model", "dataset", "space")
DEFAULT_BRANCH = "main"
# What the Hub puts in a new repository's first commit (abridged list of LFS patterns).
INITIAL_GITATTRIBUTES = (
    "*.bin filter=lfs diff=lfs merge=lfs -text\n"
    "*.parquet filter=lfs diff=lfs merge=lfs -text\n"
    "*.safetensors filter=lfs diff=lfs merge=lfs -text\n"
    "*.mp4 filter=lfs diff=lfs merge=lfs -text\n"
)


def _now() -> str:
    """A timestamp in the Hub's format (huggingface_hub parses exactly this one)."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def git_blob_oid(data: bytes) -> str:
    """The git object id of a blob: what the Hub reports as a regular file's oid and ETag."""
    return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


class HubError(Exception):
    """An HTTP error answer: status, message and the Hub's `X-Error-Code` (if any)."""

    def __init__(self, status: int, message: str, code: str | None = None, **body: object):
        super().__init__(message)
        self.status = status
        self.message = message
        self.code = code
        self.body = body  # extra JSON fields of the answer


class RepoStore:
    """Repositories with branches, tags and content-addressed commits under one folder."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.lock = threading.RLock()

    # -- repositories -------------------------------------------------------------------------
    def _dir(self, repo_type: str, repo_id: str) -> Path:
        return self.root / f"{repo_type}s" / repo_id

    def exists(self, repo_type: str, repo_id: str) -> bool:
        return (self._dir(repo_type, repo_id) / "repo.json").is_file()

    def meta(self, repo_type: str, repo_id: str) -> dict:
        path = self._dir(repo_type, repo_id) / "repo.json"
        if not path.is_file():
            raise HubError(404, "Repository not found", "RepoNotFound")
        return json.loads(path.read_text())

    def _save_meta(self, repo_type: str, repo_id: str, meta: dict) -> None:
        path = self._dir(repo_type, repo_id) / "repo.json"
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(meta, indent=1))
        os.replace(tmp, path)  # readers (not under the lock) never see a half-written file

    def create(self, repo_type: str, repo_id: str, private: bool) -> None:
        with self.lock:
            if self.exists(repo_type, repo_id):
                raise HubError(409, f"You already created this {repo_type} repo")
            repo = self._dir(repo_type, repo_id)
            (repo / "commits").mkdir(parents=True)
            (repo / "blobs").mkdir()
            self._save_meta(repo_type, repo_id, {"private": private, "created": _now(), "branches": {}, "tags": {}})
            oid = self._write_commit(
                repo_type,
                repo_id,
                None,
                "initial commit",
                {".gitattributes": self._write_blob(repo_type, repo_id, INITIAL_GITATTRIBUTES.encode())},
            )
            meta = self.meta(repo_type, repo_id)
            meta["branches"][DEFAULT_BRANCH] = oid
            self._save_meta(repo_type, repo_id, meta)

    # -- objects ------------------------------------------------------------------------------
    def _write_blob(self, repo_type: str, repo_id: str, data: bytes) -> str:
        oid = git_blob_oid(data)
        path = self._dir(repo_type, repo_id) / "blobs" / oid
        if not path.exists():
            path.write_bytes(data)
        return oid

    def blob(self, repo_type: str, repo_id: str, oid: str) -> bytes:
        return (self._dir(repo_type, repo_id) / "blobs" / oid).read_bytes()

    def _write_commit(
        self, repo_type: str, repo_id: str, parent: str | None, message: str, tree: dict[str, str]
    ) -> str:
        body = {"parent": parent, "message": message, "tree": dict(sorted(tree.items())), "date": _now()}
        text = json.dumps(body, sort_keys=True)
        oid = hashlib.sha1(text.encode()).hexdigest()
        (self._dir(repo_type, repo_id) / "commits" / f"{oid}.json").write_text(text)
        return oid

    def commit(self, repo_type: str, repo_id: str, oid: str) -> dict:
        path = self._dir(repo_type, repo_id) / "commits" / f"{oid}.json"
        return json.loads(path.read_text())

    def resolve(self, repo_type: str, repo_id: str, revision: str) -> str:
        """A branch, tag or full commit oid -> commit oid (404 RevisionNotFound otherwise)."""
        meta = self.meta(repo_type, repo_id)
        for kind in ("branches", "tags"):
            if revision in meta[kind]:
                return meta[kind][revision]
        name = revision.removeprefix("refs/heads/").removeprefix("refs/tags/")
        for kind in ("branches", "tags"):
            if name in meta[kind]:
                return meta[kind][name]
        if (
            re.fullmatch(r"[0-9a-f]{40}", revision)
            and (self._dir(repo_type, repo_id) / "commits" / f"{revision}.json").is_file()
        ):
            return revision
        raise HubError(404, f"Invalid rev id: {revision}", "RevisionNotFound")

    def tree(self, repo_type: str, repo_id: str, revision: str) -> tuple[str, dict[str, str]]:
        oid = self.resolve(repo_type, repo_id, revision)
        return oid, self.commit(repo_type, repo_id, oid)["tree"]

    # -- writes -------------------------------------------------------------------------------
    def apply_commit(
        self,
        repo_type: str,
        repo_id: str,
        branch: str,
        message: str,
        parent: str | None,
        adds: dict[str, bytes],
        deletes: list[str],
        deleted_folders: list[str],
    ) -> str:
        with self.lock:
            meta = self.meta(repo_type, repo_id)
            if branch not in meta["branches"]:
                if branch in meta["tags"]:
                    raise HubError(400, f"Cannot commit to tag {branch}: only branches can be committed to")
                raise HubError(404, f"Invalid rev id: {branch}", "RevisionNotFound")
            head = meta["branches"][branch]
            if parent is not None and parent != head:
                raise HubError(412, f"Parent commit {parent} is not the head of {branch} ({head})")
            tree = dict(self.commit(repo_type, repo_id, head)["tree"])
            for path in deletes:
                if path not in tree:
                    raise HubError(404, f"A file with this name doesn't exist: {path}", "EntryNotFound")
                del tree[path]
            for folder in deleted_folders:
                prefix = folder.rstrip("/") + "/"
                for path in [p for p in tree if p.startswith(prefix)]:
                    del tree[path]
            for path, data in adds.items():
                tree[path] = self._write_blob(repo_type, repo_id, data)
            oid = self._write_commit(repo_type, repo_id, head, message, tree)
            meta["branches"][branch] = oid
            self._save_meta(repo_type, repo_id, meta)
            return oid

    def create_ref(self, repo_type: str, repo_id: str, kind: str, name: str, revision: str) -> None:
        with self.lock:
            meta = self.meta(repo_type, repo_id)
            if name in meta[kind]:
                label = "Branch" if kind == "branches" else "Tag"
                raise HubError(409, f"{label} {name} already exists")
            meta[kind][name] = self.resolve(repo_type, repo_id, revision)
            self._save_meta(repo_type, repo_id, meta)

    def delete_tag(self, repo_type: str, repo_id: str, name: str) -> None:
        with self.lock:
            meta = self.meta(repo_type, repo_id)
            if name not in meta["tags"]:
                raise HubError(404, f"Invalid rev id: {name}", "RevisionNotFound")
            del meta["tags"][name]
            self._save_meta(repo_type, repo_id, meta)


class LoopbackHub:
    """The server: `with LoopbackHub(tmp, tokens) as hub: ... hub.endpoint ...`."""

    def __init__(self, root: Path, tokens: dict[str, str] | None = None):
        self.store = RepoStore(root)
        self.tokens = dict(tokens or {})
        self.requests: list[tuple[str, str]] = []  # (method, path) of every request, for tests
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), _handler_class(self))
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    @property
    def endpoint(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}"

    def start(self) -> LoopbackHub:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join()

    def __enter__(self) -> LoopbackHub:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


_API_REPO = re.compile(r"^/api/(models|datasets|spaces)/([^/]+)/([^/]+)(?:/(.*))?$")
_RESOLVE = re.compile(r"^/(?:(datasets|spaces)/)?([^/]+)/([^/]+)/resolve/([^/]+)/(.+)$")


def _handler_class(hub: LoopbackHub) -> type[BaseHTTPRequestHandler]:
    store = hub.store

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"  # keep-alive, as the client's session expects

        def log_message(self, format: str, *args: object) -> None:  # a quiet server
            pass

        # -- plumbing -------------------------------------------------------------------------
        def _body(self) -> bytes:
            length = int(self.headers.get("Content-Length") or 0)
            return self.rfile.read(length) if length else b""

        def _send(
            self,
            status: int,
            body: bytes = b"",
            headers: dict[str, str] | None = None,
            content_type: str = "application/json",
        ) -> None:
            self.send_response(status)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            for key, value in (headers or {}).items():
                self.send_header(key, value)
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, status: int, obj: object) -> None:
            self._send(status, json.dumps(obj).encode())

        def _error(self, err: HubError) -> None:
            headers = {"X-Error-Message": err.message}
            if err.code:
                headers["X-Error-Code"] = err.code
            self._send(err.status, json.dumps({"error": err.message, **err.body}).encode(), headers)

        def _token_role(self) -> str | None:
            """The caller's role ("read"/"write"), None when anonymous; 401 on an unknown token."""
            auth = self.headers.get("Authorization") or ""
            if not auth:
                return None
            token = auth.removeprefix("Bearer ").strip()
            if token not in hub.tokens:
                raise HubError(401, "Invalid credentials in Authorization header")
            return hub.tokens[token]

        def _require_write(self) -> None:
            role = self._token_role()
            if role is None:
                raise HubError(401, "You must be authenticated to write to the Hub")
            if role != "write":
                raise HubError(403, "You don't have the rights to write to this repository (read-only token)")

        def _require_read(self, repo_type: str, repo_id: str) -> None:
            role = self._token_role()
            if store.meta(repo_type, repo_id)["private"] and role is None:
                raise HubError(401, "Repository not found", "RepoNotFound")

        def _dispatch(self) -> None:
            hub.requests.append((self.command, self.path))
            url = urlsplit(self.path)
            query = parse_qs(url.query)
            body = self._body() if self.command in ("POST", "PUT", "DELETE") else b""
            try:
                if url.path == "/api/repos/create" and self.command == "POST":
                    return self._create_repo(json.loads(body or b"{}"))
                if url.path == "/api/validate-yaml" and self.command == "POST":
                    return self._validate_yaml(json.loads(body or b"{}"))
                match = _API_REPO.match(url.path)
                if match:
                    kind, org, name, rest = match.groups()
                    return self._repo_api(kind[:-1], f"{unquote(org)}/{unquote(name)}", rest or "", query, body)
                match = _RESOLVE.match(url.path)
                if match and self.command in ("HEAD", "GET"):
                    prefix, org, name, rev, path = match.groups()
                    repo_type = prefix[:-1] if prefix else "model"
                    return self._resolve(
                        repo_type,
                        f"{unquote(org)}/{unquote(name)}",
                        unquote(rev),
                        "/".join(unquote(p) for p in path.split("/")),
                    )
                raise HubError(404, f"Route not found: {self.command} {url.path}")
            except HubError as err:
                self._error(err)

        do_GET = do_HEAD = do_POST = do_DELETE = _dispatch

        # -- routes ---------------------------------------------------------------------------
        def _create_repo(self, payload: dict) -> None:
            self._require_write()
            repo_type = payload.get("type") or "model"
            if repo_type not in REPO_TYPES:
                raise HubError(400, f"Invalid repo type: {repo_type}")
            name, org = payload.get("name"), payload.get("organization")
            if not name or not org:
                raise HubError(400, "This test hub needs an organization/namespace in the repo id")
            # huggingface_hub 1.x sends `visibility`; older clients send the `private` flag.
            visibility = payload.get("visibility")
            if visibility not in (None, "public", "private"):
                raise HubError(400, f"Invalid visibility for a {repo_type} repo: {visibility}")
            private = visibility == "private" if visibility is not None else bool(payload.get("private"))
            repo_id = f"{org}/{name}"
            prefix = "" if repo_type == "model" else f"{repo_type}s/"
            url = f"{hub.endpoint}/{prefix}{repo_id}"
            with store.lock:
                if store.exists(repo_type, repo_id):
                    raise HubError(409, f"You already created this {repo_type} repo", url=url)
                store.create(repo_type, repo_id, private)
            self._json(200, {"url": url, "name": repo_id})

        def _validate_yaml(self, payload: dict) -> None:
            content = payload.get("content") or ""
            match = re.match(r"^---\s*\n(.*?)\n---\s*\n", content, re.DOTALL)
            if not match:
                return self._json(200, {"errors": [], "warnings": [{"message": "Empty or missing yaml metadata"}]})
            try:
                data = yaml.safe_load(match.group(1))
            except yaml.YAMLError as exc:
                return self._json(400, {"errors": [{"message": f"Invalid YAML: {exc}".splitlines()[0]}]})
            if not isinstance(data, dict):
                return self._json(400, {"errors": [{"message": "YAML metadata must be a mapping"}]})
            self._json(200, {"errors": [], "warnings": []})

        def _repo_api(self, repo_type: str, repo_id: str, rest: str, query: dict, body: bytes) -> None:
            parts = rest.split("/") if rest else []
            action = parts[0] if parts else ""
            arg = unquote(parts[1]) if len(parts) > 1 else None
            if self.command == "GET":
                self._require_read(repo_type, repo_id)
                if action == "":
                    return self._info(repo_type, repo_id, DEFAULT_BRANCH)
                if action == "revision" and arg:
                    return self._info(repo_type, repo_id, arg)
                if action == "refs":
                    return self._refs(repo_type, repo_id)
                if action == "tree" and arg:
                    sub = "/".join(unquote(p) for p in parts[2:])
                    recursive = query.get("recursive", ["false"])[0].lower() in ("1", "true")
                    return self._tree(repo_type, repo_id, arg, sub, recursive)
            elif self.command == "POST" and arg:
                self._require_write()
                store.meta(repo_type, repo_id)  # 404 RepoNotFound first, as the Hub does
                payload_is_json = action in ("preupload", "branch", "tag")
                payload = json.loads(body or b"{}") if payload_is_json else None
                if action == "preupload":
                    return self._preupload(repo_type, repo_id, arg, payload)
                if action == "commit":
                    return self._commit(repo_type, repo_id, arg, body, parse_qs(urlsplit(self.path).query))
                if action == "branch":
                    store.create_ref(
                        repo_type, repo_id, "branches", arg, payload.get("startingPoint") or DEFAULT_BRANCH
                    )
                    return self._json(200, {})
                if action == "tag":
                    store.create_ref(repo_type, repo_id, "tags", payload["tag"], arg)
                    return self._json(200, {})
            elif self.command == "DELETE" and action == "tag" and arg:
                self._require_write()
                store.delete_tag(repo_type, repo_id, arg)
                return self._json(200, {})
            raise HubError(404, f"Route not found: {self.command} {self.path}")

        def _info(self, repo_type: str, repo_id: str, revision: str) -> None:
            oid, tree = store.tree(repo_type, repo_id, revision)
            meta = store.meta(repo_type, repo_id)
            commit = store.commit(repo_type, repo_id, oid)
            self._json(
                200,
                {
                    "_id": hashlib.sha1(f"{repo_type}/{repo_id}".encode()).hexdigest()[:24],
                    "id": repo_id,
                    "author": repo_id.split("/")[0],
                    "sha": oid,
                    "private": meta["private"],
                    "gated": False,
                    "disabled": False,
                    "downloads": 0,
                    "likes": 0,
                    "tags": [],
                    "createdAt": meta["created"],
                    "lastModified": commit["date"],
                    "siblings": [{"rfilename": path} for path in tree],
                    "xetEnabled": False,
                },
            )

        def _refs(self, repo_type: str, repo_id: str) -> None:
            meta = store.meta(repo_type, repo_id)
            self._json(
                200,
                {
                    "branches": [
                        {"name": n, "ref": f"refs/heads/{n}", "targetCommit": o} for n, o in meta["branches"].items()
                    ],
                    "tags": [{"name": n, "ref": f"refs/tags/{n}", "targetCommit": o} for n, o in meta["tags"].items()],
                    "converts": [],
                },
            )

        def _tree(self, repo_type: str, repo_id: str, revision: str, sub: str, recursive: bool) -> None:
            _, tree = store.tree(repo_type, repo_id, revision)
            prefix = sub.strip("/") + "/" if sub.strip("/") else ""
            if prefix and not any(p.startswith(prefix) for p in tree):
                raise HubError(404, f"Entry not found: {sub}", "EntryNotFound")
            entries: dict[str, dict] = {}
            for path, oid in tree.items():
                if not path.startswith(prefix):
                    continue
                parts = path[len(prefix) :].split("/")
                depth = len(parts) if recursive else 1
                for i in range(1, min(depth, len(parts) - 1) + 1):  # the folders on the way
                    folder = prefix + "/".join(parts[:i])
                    entries.setdefault(folder, {"type": "directory", "oid": "", "size": 0, "path": folder})
                if recursive or len(parts) == 1:
                    size = len(store.blob(repo_type, repo_id, oid))
                    entries[path] = {"type": "file", "oid": oid, "size": size, "path": path}
            self._json(200, list(entries.values()))

        def _preupload(self, repo_type: str, repo_id: str, revision: str, payload: dict) -> None:
            _, tree = store.tree(repo_type, repo_id, revision)
            # Every file goes inline in the commit ("regular"): no LFS or xet transfer to emulate.
            self._json(
                200,
                {
                    "files": [
                        {"path": f["path"], "uploadMode": "regular", "shouldIgnore": False, "oid": tree.get(f["path"])}
                        for f in payload.get("files", [])
                    ]
                },
            )

        def _commit(self, repo_type: str, repo_id: str, revision: str, body: bytes, query: dict) -> None:
            if query.get("create_pr"):
                raise HubError(400, "Pull requests are not supported by this test hub")
            header: dict = {}
            adds: dict[str, bytes] = {}
            deletes: list[str] = []
            folders: list[str] = []
            for line in body.splitlines():
                if not line.strip():
                    continue
                item = json.loads(line)
                key, value = item["key"], item["value"]
                if key == "header":
                    header = value
                elif key == "file":
                    if value.get("encoding") != "base64":
                        raise HubError(400, f"Unsupported encoding for {value.get('path')}")
                    adds[value["path"]] = base64.b64decode(value["content"])
                elif key == "deletedFile":
                    deletes.append(value["path"])
                elif key == "deletedFolder":
                    folders.append(value["path"])
                else:
                    raise HubError(
                        400, f"Unsupported commit operation {key!r} (this test hub stores regular files only)"
                    )
            if not header.get("summary"):
                raise HubError(400, "Commit summary is required")
            oid = store.apply_commit(
                repo_type, repo_id, revision, header["summary"], header.get("parentCommit"), adds, deletes, folders
            )
            prefix = "" if repo_type == "model" else f"{repo_type}s/"
            self._json(
                200,
                {
                    "success": True,
                    "commitOid": oid,
                    "pullRequestUrl": None,
                    "commitUrl": f"{hub.endpoint}/{prefix}{repo_id}/commit/{oid}",
                },
            )

        def _resolve(self, repo_type: str, repo_id: str, revision: str, path: str) -> None:
            self._require_read(repo_type, repo_id)
            oid, tree = store.tree(repo_type, repo_id, revision)
            if path not in tree:
                raise HubError(404, f"Entry not found: {path}", "EntryNotFound")
            data = store.blob(repo_type, repo_id, tree[path])
            self._send(
                200, data, {"X-Repo-Commit": oid, "ETag": f'"{tree[path]}"'}, content_type="application/octet-stream"
            )

    return Handler
