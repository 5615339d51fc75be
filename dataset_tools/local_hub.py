"""A small Hugging Face Hub-compatible HTTP server for offline labs and for our tests.

It speaks the subset of the Hub's REST API that `huggingface_hub` uses to create repos, commit files
(regular and LFS, basic transfer), tag, list and download them (with HTTP range requests), so
`bcrl-hub` and LeRobot's own hub code run unmodified against `HF_ENDPOINT=http://127.0.0.1:<port>`.
Xet storage is not spoken: clients must set `HF_HUB_DISABLE_XET=1` (bcrl-hub does when the endpoint
is not huggingface.co). Run: `bcrl-local-hub --port=8765 --storage=outputs/hub`.
"""

from __future__ import annotations

import base64
import hashlib
import json
import re
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlsplit

LFS_EXTENSIONS = (".parquet", ".mp4", ".safetensors", ".bin", ".pt", ".png", ".jpg", ".arrow", ".rrd", ".npz")
LFS_MIN_SIZE = 10 * 1024 * 1024
PREFIX = {"model": "", "dataset": "datasets/", "space": "spaces/"}


def git_blob_oid(content: bytes) -> str:
    return hashlib.sha1(b"blob %d\0" % len(content) + content).hexdigest()


@dataclass
class FileEntry:
    sha256: str
    size: int
    git_oid: str  # blob id of what git stores: the content, or the LFS pointer file
    lfs: bool


@dataclass
class Repo:
    repo_type: str
    repo_id: str
    private: bool
    commits: dict[str, dict[str, FileEntry]] = field(default_factory=dict)
    branches: dict[str, str] = field(default_factory=dict)
    tags: dict[str, str] = field(default_factory=dict)

    def resolve(self, revision: str) -> str | None:
        revision = unquote(revision)
        if revision in self.branches:
            return self.branches[revision]
        if revision in self.tags:
            return self.tags[revision]
        if revision in self.commits:
            return revision
        return None


@dataclass
class Faults:
    """Failures the tests inject into downloads, keyed by path in repo."""

    truncate_once: set[str] = field(default_factory=set)  # cut the connection half-way, once
    truncate_always: set[str] = field(default_factory=set)
    corrupt: set[str] = field(default_factory=set)  # serve flipped bytes with the right headers


class HubState:
    def __init__(self, storage: Path, tokens: set[str] | None = None):
        self.objects = Path(storage) / "objects"
        self.objects.mkdir(parents=True, exist_ok=True)
        self.repos: dict[tuple[str, str], Repo] = {}
        self.tokens = tokens or set()  # empty: anonymous writes allowed, private repos readable by anyone
        self.faults = Faults()
        self.log: list[tuple[str, str, str | None]] = []  # (method, path, Range header)
        self.lock = threading.Lock()

    def object_path(self, sha256: str) -> Path:
        return self.objects / sha256

    def put_object(self, content: bytes) -> str:
        sha256 = hashlib.sha256(content).hexdigest()
        path = self.object_path(sha256)
        if not path.exists():
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(content)
            tmp.replace(path)
        return sha256


def _lfs_pointer(sha256: str, size: int) -> bytes:
    return f"version https://git-lfs.github.com/spec/v1\noid sha256:{sha256}\nsize {size}\n".encode()


class HubHandler(BaseHTTPRequestHandler):
    server: "LocalHub"
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):  # quiet
        pass

    # -- plumbing ------------------------------------------------------------------------------------
    def _body(self) -> bytes:
        return self._request_body

    def _read_body(self) -> bytes:
        # Read every request body whole, used or not: a leftover would corrupt the next request on the
        # same keep-alive connection.
        if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
            chunks = []
            while True:
                size = int(self.rfile.readline().strip().split(b";")[0], 16)
                if size == 0:
                    self.rfile.readline()
                    break
                chunks.append(self.rfile.read(size))
                self.rfile.readline()
            return b"".join(chunks)
        return self.rfile.read(int(self.headers.get("Content-Length") or 0))

    def _send(self, status: int, payload=None, headers: dict | None = None, body: bytes | None = None):
        if body is None:
            body = json.dumps(payload if payload is not None else {}).encode()
            headers = {"Content-Type": "application/json", **(headers or {})}
        self.send_response(status)
        for key, value in (headers or {}).items():
            self.send_header(key, str(value))
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _error(self, status: int, code: str, message: str):
        self._send(status, {"error": message}, headers={"X-Error-Code": code, "X-Error-Message": message})

    def _authorized(self) -> bool:
        if not self.server.state.tokens:
            return True
        auth = self.headers.get("Authorization", "")
        return auth.startswith("Bearer ") and auth[7:] in self.server.state.tokens

    def _repo(self, repo_type: str, repo_id: str, write: bool = False) -> Repo | None:
        repo = self.server.state.repos.get((repo_type, repo_id))
        if repo is None or ((repo.private or write) and not self._authorized()):
            # like the Hub: a private repo you may not read does not exist for you
            self._error(401 if not self._authorized() else 404, "RepoNotFound", f"Repository {repo_id} not found")
            return None
        return repo

    def _revision(self, repo_type: str, repo_id: str, rev: str, write: bool = False) -> tuple[Repo, str] | None:
        """(repo, commit sha) for a branch, tag or sha; sends the Hub's error and returns None if missing."""
        repo = self._repo(repo_type, repo_id, write=write)
        if repo is None:
            return None
        sha = repo.resolve(rev)
        if sha is None:
            self._error(404, "RevisionNotFound", f"Invalid rev id: {rev}")
            return None
        return repo, sha

    @property
    def base_url(self) -> str:
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}"

    # -- routing -------------------------------------------------------------------------------------
    ROUTES = [
        ("POST", r"/api/repos/create", "create_repo"),
        ("POST", r"/api/validate-yaml", "validate_yaml"),
        ("GET", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/revision/(?P<rev>[^/]+)", "repo_info"),
        ("GET", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)", "repo_info"),
        ("GET", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/refs", "refs"),
        ("GET", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/tree/(?P<rev>[^/]+)(?P<path>/.*)?", "tree"),
        ("POST", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/paths-info/(?P<rev>[^/]+)", "paths_info"),
        ("POST", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/preupload/(?P<rev>[^/]+)", "preupload"),
        ("POST", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/commit/(?P<rev>[^/]+)", "commit"),
        ("POST", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/tag/(?P<rev>[^/]+)", "create_tag"),
        ("DELETE", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/tag/(?P<rev>[^/]+)", "delete_tag"),
        ("POST", r"/api/(?P<t>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)/branch/(?P<rev>[^/]+)", "create_branch"),
        ("POST", r"/(?:(?P<t>datasets|spaces)/)?(?P<repo>[^/]+/[^/]+)\.git/info/lfs/objects/batch", "lfs_batch"),
        ("PUT", r"/lfs-upload/(?P<oid>[0-9a-f]{64})", "lfs_upload"),
        ("POST", r"/lfs-verify/(?P<oid>[0-9a-f]{64})", "lfs_verify"),
        ("GET", r"/(?:(?P<t>datasets|spaces)/)?(?P<repo>[^/]+/[^/]+)/resolve/(?P<rev>[^/]+)/(?P<path>.+)", "resolve"),
        ("HEAD", r"/(?:(?P<t>datasets|spaces)/)?(?P<repo>[^/]+/[^/]+)/resolve/(?P<rev>[^/]+)/(?P<path>.+)", "resolve"),
    ]

    def _dispatch(self):
        url = urlsplit(self.path)
        self.query = parse_qs(url.query)
        self.server.state.log.append((self.command, url.path, self.headers.get("Range")))
        self._request_body = self._read_body() if self.command in ("POST", "PUT", "DELETE") else b""
        for method, pattern, name in self.ROUTES:
            match = re.fullmatch(pattern, url.path)
            if method == self.command and match:
                args = {k: v for k, v in match.groupdict().items()}
                if "t" in args:
                    args["t"] = {"models": "model", "datasets": "dataset", "spaces": "space", None: "model"}[args["t"]]
                try:
                    with self.server.state.lock if self.command not in ("GET", "HEAD") else _nullcontext():
                        getattr(self, name)(**args)
                except (BrokenPipeError, ConnectionResetError):
                    pass
                return
        self._error(404, "NotFound", f"no route for {self.command} {url.path}")

    do_GET = do_POST = do_PUT = do_HEAD = do_DELETE = _dispatch

    # -- repos ---------------------------------------------------------------------------------------
    def create_repo(self):
        payload = json.loads(self._body() or b"{}")
        if not self._authorized():
            return self._error(401, "Unauthorized", "invalid token")
        repo_type = payload.get("type") or "model"
        repo_id = f"{payload['organization']}/{payload['name']}" if payload.get("organization") else payload["name"]
        if "/" not in repo_id:
            repo_id = f"user/{repo_id}"
        url = f"{self.base_url}/{PREFIX[repo_type]}{repo_id}"
        state = self.server.state
        if (repo_type, repo_id) in state.repos:
            return self._send(409, {"error": "You already created this repo", "url": url})
        private = bool(payload.get("private")) or payload.get("visibility") == "private"
        repo = Repo(repo_type, repo_id, private)
        initial = hashlib.sha1(f"{repo_type}/{repo_id}/{time.time_ns()}".encode()).hexdigest()
        repo.commits[initial] = {}
        repo.branches["main"] = initial
        state.repos[(repo_type, repo_id)] = repo
        self._send(200, {"url": url, "name": repo_id})

    def validate_yaml(self):
        self._send(200, {"errors": [], "warnings": []})  # accepted as is: no card schema here

    def repo_info(self, t, repo, rev="main"):
        found = self._revision(t, repo, rev)
        if found is None:
            return
        r, sha = found
        files = r.commits[sha]
        self._send(
            200,
            {
                "id": repo,
                "_id": repo,
                "sha": sha,
                "private": r.private,
                "siblings": [{"rfilename": p} for p in sorted(files)],
                "tags": [],
                "downloads": 0,
                "likes": 0,
                "lastModified": "2026-01-01T00:00:00.000Z",
            },
        )

    def refs(self, t, repo):
        r = self._repo(t, repo)
        if r is None:
            return
        self._send(
            200,
            {
                "branches": [{"name": n, "ref": f"refs/heads/{n}", "targetCommit": s} for n, s in r.branches.items()],
                "tags": [{"name": n, "ref": f"refs/tags/{n}", "targetCommit": s} for n, s in r.tags.items()],
                "converts": [],
            },
        )

    def _entry_json(self, path: str, entry: FileEntry) -> dict:
        item = {"type": "file", "path": path, "size": entry.size, "oid": entry.git_oid}
        if entry.lfs:
            item["lfs"] = {"oid": entry.sha256, "size": entry.size, "pointerSize": len(_lfs_pointer(entry.sha256, entry.size))}
        return item

    def _listing(self, files: dict[str, FileEntry], prefix: str, recursive: bool) -> list[dict]:
        prefix = prefix.strip("/")
        out, dirs = [], set()
        for path in sorted(files):
            if prefix and not path.startswith(prefix + "/"):
                continue
            rest = path[len(prefix) + 1 :] if prefix else path
            parts = rest.split("/")
            for depth in range(1, len(parts)):
                if not recursive and depth > 1:
                    break
                directory = "/".join(([prefix] if prefix else []) + parts[:depth])
                if directory not in dirs:
                    dirs.add(directory)
                    out.append({"type": "directory", "path": directory, "oid": hashlib.sha1(directory.encode()).hexdigest()})
            if recursive or len(parts) == 1:
                out.append(self._entry_json(path, files[path]))
        return out

    def tree(self, t, repo, rev, path=None):
        found = self._revision(t, repo, rev)
        if found is None:
            return
        r, sha = found
        recursive = self.query.get("recursive", ["false"])[0].lower() in ("1", "true")
        self._send(200, self._listing(r.commits[sha], unquote(path or ""), recursive))

    def paths_info(self, t, repo, rev):
        found = self._revision(t, repo, rev)
        if found is None:
            return
        r, sha = found
        body = self._body()
        content_type = self.headers.get("Content-Type", "")
        if "json" in content_type:
            paths = json.loads(body).get("paths", [])
        else:
            paths = parse_qs(body.decode()).get("paths", [])
        files = r.commits[sha]
        self._send(200, [self._entry_json(p, files[p]) for p in paths if p in files])

    # -- uploads -------------------------------------------------------------------------------------
    def preupload(self, t, repo, rev):
        r = self._repo(t, repo, write=True)
        if r is None:
            return
        payload = json.loads(self._body())
        current = r.commits.get(r.resolve(rev) or "", {})
        files = []
        for f in payload["files"]:
            sample = base64.b64decode(f["sample"])
            lfs = f["path"].endswith(LFS_EXTENSIONS) or f["size"] >= LFS_MIN_SIZE or b"\0" in sample
            existing = current.get(f["path"])
            files.append(
                {
                    "path": f["path"],
                    "uploadMode": "lfs" if lfs else "regular",
                    "shouldIgnore": False,
                    "oid": existing.git_oid if existing and not existing.lfs else None,
                }
            )
        self._send(200, {"files": files, "commitOid": r.resolve(rev)})

    def lfs_batch(self, t, repo):
        r = self._repo(t or "model", repo, write=True)
        if r is None:
            return
        payload = json.loads(self._body())
        objects = []
        for obj in payload["objects"]:
            item = {"oid": obj["oid"], "size": obj["size"], "authenticated": True}
            if not self.server.state.object_path(obj["oid"]).exists():
                item["actions"] = {
                    "upload": {"href": f"{self.base_url}/lfs-upload/{obj['oid']}", "header": {}},
                    "verify": {"href": f"{self.base_url}/lfs-verify/{obj['oid']}", "header": {}},
                }
            objects.append(item)
        self._send(200, {"transfer": "basic", "objects": objects}, headers={"Content-Type": "application/vnd.git-lfs+json"})

    def lfs_upload(self, oid):
        content = self._body()
        if hashlib.sha256(content).hexdigest() != oid:
            return self._error(400, "BadRequest", f"content does not match oid {oid}")
        self.server.state.put_object(content)
        self._send(200, {})

    def lfs_verify(self, oid):
        exists = self.server.state.object_path(oid).exists()
        self._send(200 if exists else 404, {})

    def commit(self, t, repo, rev):
        found = self._revision(t, repo, rev, write=True)
        if found is None:
            return
        r, parent = found
        files = dict(r.commits[parent])
        state = self.server.state
        lines = [json.loads(line) for line in self._body().splitlines() if line.strip()]
        for line in lines:
            key, value = line["key"], line["value"]
            if key == "file":
                content = base64.b64decode(value["content"]) if value.get("encoding") == "base64" else value["content"].encode()
                files[value["path"]] = FileEntry(state.put_object(content), len(content), git_blob_oid(content), lfs=False)
            elif key == "lfsFile":
                if not state.object_path(value["oid"]).exists():
                    return self._error(400, "BadRequest", f"LFS object {value['oid']} was never uploaded")
                pointer = _lfs_pointer(value["oid"], value["size"])
                files[value["path"]] = FileEntry(value["oid"], value["size"], git_blob_oid(pointer), lfs=True)
            elif key == "deletedFile":
                files.pop(value["path"], None)
            elif key == "deletedFolder":
                folder = value["path"].rstrip("/") + "/"
                files = {p: e for p, e in files.items() if not p.startswith(folder)}
        sha = hashlib.sha1(json.dumps([parent, lines, time.time_ns()], sort_keys=True).encode()).hexdigest()
        r.commits[sha] = files
        branch = unquote(rev) if unquote(rev) in r.branches else "main"
        r.branches[branch] = sha
        url = f"{self.base_url}/{PREFIX[t]}{repo}/commit/{sha}"
        self._send(200, {"commitUrl": url, "commitOid": sha, "pullRequestUrl": None})

    def create_tag(self, t, repo, rev):
        found = self._revision(t, repo, rev, write=True)
        if found is None:
            return
        r, sha = found
        payload = json.loads(self._body() or b"{}")
        if payload["tag"] in r.tags:
            return self._error(409, "Conflict", f"tag {payload['tag']} already exists")
        r.tags[payload["tag"]] = sha
        self._send(200, {})

    def delete_tag(self, t, repo, rev):
        r = self._repo(t, repo, write=True)
        if r is None:
            return
        if r.tags.pop(unquote(rev), None) is None:
            return self._error(404, "RevisionNotFound", f"no tag {rev}")
        self._send(200, {})

    def create_branch(self, t, repo, rev):
        r = self._repo(t, repo, write=True)
        if r is None:
            return
        payload = json.loads(self._body() or b"{}")
        start = r.resolve(payload.get("startingPoint") or "main")
        if unquote(rev) in r.branches:
            return self._error(409, "Conflict", f"branch {rev} already exists")
        r.branches[unquote(rev)] = start
        self._send(200, {})

    # -- downloads -----------------------------------------------------------------------------------
    def resolve(self, t, repo, rev, path):
        found = self._revision(t or "model", repo, rev)
        if found is None:
            return
        r, sha = found
        path = unquote(path)
        entry = r.commits[sha].get(path)
        if entry is None:
            return self._error(404, "EntryNotFound", f"{path} does not exist at {rev}")
        headers = {
            "X-Repo-Commit": sha,
            "ETag": f'"{entry.sha256 if entry.lfs else entry.git_oid}"',
            "Accept-Ranges": "bytes",
            "Content-Type": "application/octet-stream",
        }
        if entry.lfs:
            headers["X-Linked-Etag"] = f'"{entry.sha256}"'
            headers["X-Linked-Size"] = str(entry.size)
        content = self.server.state.object_path(entry.sha256).read_bytes()
        faults = self.server.state.faults
        if path in faults.corrupt:
            content = bytes(b ^ 0xFF for b in content[:64]) + content[64:]
        start = 0
        range_header = self.headers.get("Range")
        if range_header and (m := re.fullmatch(r"bytes=(\d+)-(\d*)", range_header)):
            start = int(m.group(1))
            end = int(m.group(2)) if m.group(2) else len(content) - 1
            body = content[start : end + 1]
            headers["Content-Range"] = f"bytes {start}-{start + len(body) - 1}/{len(content)}"
            status = 206
        else:
            body, status = content, 200
        if self.command == "HEAD":
            self.send_response(status)
            for key, value in headers.items():
                self.send_header(key, value)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            return
        truncate = path in faults.truncate_always or path in faults.truncate_once
        if truncate and len(body) > 1:
            faults.truncate_once.discard(path)
            self.send_response(status)
            for key, value in headers.items():
                self.send_header(key, value)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body[: len(body) // 2])
            self.wfile.flush()
            self.close_connection = True
            return
        self._send(status, headers=headers, body=body)


class _nullcontext:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class LocalHub(ThreadingHTTPServer):
    """`with LocalHub(storage) as hub: os.environ["HF_ENDPOINT"] = hub.url`."""

    daemon_threads = True

    def __init__(self, storage: Path, host: str = "127.0.0.1", port: int = 0, tokens: set[str] | None = None):
        super().__init__((host, port), HubHandler)
        self.state = HubState(storage, tokens)
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self.server_address[:2]
        return f"http://{host}:{port}"

    def start(self) -> "LocalHub":
        self._thread = threading.Thread(target=self.serve_forever, daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self.shutdown()
        self.server_close()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


def main() -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8765)
    parser.add_argument("--storage", default="outputs/local_hub")
    parser.add_argument("--token", action="append", default=[], help="accepted write token (repeatable)")
    args = parser.parse_args()
    hub = LocalHub(Path(args.storage), args.host, args.port, set(args.token))
    print(f"local hub at {hub.url} (storage {args.storage}); export HF_ENDPOINT={hub.url} HF_HUB_DISABLE_XET=1")
    try:
        hub.serve_forever()
    except KeyboardInterrupt:
        hub.server_close()


if __name__ == "__main__":
    main()
