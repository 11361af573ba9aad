"""A client for Sylva's HTTP API (openapi.yaml at the repository root is the contract).

Only the Python standard library: nothing to install beside it.

    from sylva_client import Client
    c = Client("http://127.0.0.1:8080", api_key=None)
    lidar = c.upload("plot.laz", "lidar")
    colmap = c.upload("project.zip", "colmap")
    job = c.submit({"lidar": lidar, "colmap": colmap}, params={"until": "segment"})
    job = c.wait(job["id"], on_event=print)
    c.download(job["id"], "segment/trees.csv", "trees.csv")

Errors are `SylvaError` and its subclasses, built from the server's problem+json answers
(RFC 9457): `status`, `type`, `title`, `detail` and, for invalid input, `errors`.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import urllib.error
import urllib.parse
import urllib.request
from typing import Any, Callable, Dict, Iterator, Optional, Tuple

__all__ = [
    "Client",
    "SylvaError",
    "BadRequest",
    "Unauthorized",
    "Forbidden",
    "NotFound",
    "Conflict",
    "Unprocessable",
    "TooManyRequests",
    "ServerError",
    "Unavailable",
    "ChecksumMismatch",
]

TERMINAL = ("succeeded", "failed", "canceled")


class SylvaError(Exception):
    """An error answer of the API (problem+json) or a failure of the client's own checks."""

    def __init__(self, status: int, title: str, detail: str = "", type_: str = "",
                 errors: Optional[list] = None, body: Any = None):
        super().__init__(f"{status} {title}: {detail}" if detail else f"{status} {title}")
        self.status = status
        self.title = title
        self.detail = detail
        self.type = type_
        self.errors = errors or []
        self.body = body


class BadRequest(SylvaError):
    """400."""


class Unauthorized(SylvaError):
    """401: no key, or not a valid one."""


class Forbidden(SylvaError):
    """403."""


class NotFound(SylvaError):
    """404: no such upload, job or artifact (or one of another key)."""


class Conflict(SylvaError):
    """409: the request does not fit the record's state."""


class Unprocessable(SylvaError):
    """422: the input is unusable; `errors` says where."""


class TooManyRequests(SylvaError):
    """429."""


class ServerError(SylvaError):
    """500 and other 5xx."""


class Unavailable(ServerError):
    """503: a tool or service the server needs is missing."""


class ChecksumMismatch(SylvaError):
    """A download's bytes do not hash to the sha256 the server listed."""


_BY_STATUS = {400: BadRequest, 401: Unauthorized, 403: Forbidden, 404: NotFound, 409: Conflict,
              422: Unprocessable, 429: TooManyRequests, 503: Unavailable}


def _error(status: int, reason: str, raw: bytes) -> SylvaError:
    cls = _BY_STATUS.get(status, ServerError if status >= 500 else SylvaError)
    try:
        p = json.loads(raw.decode("utf-8"))
    except (ValueError, UnicodeDecodeError):
        p = None
    if isinstance(p, dict):
        return cls(status, p.get("title", reason), p.get("detail", ""), p.get("type", ""),
                   p.get("errors"), p)
    return cls(status, reason, raw.decode("utf-8", "replace")[:500])


def _sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class Client:
    """One server and one API key (None where the server asks for none).

    `retries` is how many times a part upload or a download is retried after a dropped
    connection or a 5xx answer, `backoff` the first wait between tries in seconds (doubled each
    time).
    """

    def __init__(self, base_url: str, api_key: Optional[str] = None, timeout: float = 60.0,
                 retries: int = 3, backoff: float = 0.5):
        self.base = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self.retries = retries
        self.backoff = backoff

    # -- plumbing ---------------------------------------------------------------------------

    def _request(self, method: str, path: str, body: Optional[bytes] = None,
                 headers: Optional[Dict[str, str]] = None, stream: bool = False):
        h = dict(headers or {})
        if self.api_key:
            h["Authorization"] = f"Bearer {self.api_key}"
        url = path if path.startswith("http") else self.base + path
        req = urllib.request.Request(url, data=body, headers=h, method=method)
        try:
            resp = urllib.request.urlopen(req, timeout=self.timeout)
        except urllib.error.HTTPError as e:
            raise _error(e.code, e.reason, e.read()) from None
        if stream:
            return resp
        with resp:
            return resp.status, resp.read()

    def _json(self, method: str, path: str, payload: Any = None,
              headers: Optional[Dict[str, str]] = None) -> Any:
        h = dict(headers or {})
        body = None
        if payload is not None:
            body = json.dumps(payload).encode("utf-8")
            h["Content-Type"] = "application/json"
        _, raw = self._request(method, path, body, h)
        return json.loads(raw.decode("utf-8")) if raw else None

    def _retrying(self, what: Callable[[], Any]) -> Any:
        wait = self.backoff
        for attempt in range(self.retries + 1):
            try:
                return what()
            except (ServerError, urllib.error.URLError, ConnectionError, TimeoutError):
                if attempt == self.retries:
                    raise
                time.sleep(wait)
                wait *= 2

    # -- the service ------------------------------------------------------------------------

    def info(self) -> dict:
        """`GET /v1/info`: the server's version and what it can do."""
        return self._json("GET", "/v1/info")

    def options(self) -> dict:
        """`GET /v1/options`: the JSON Schema of a job's `params`, with every default."""
        return self._json("GET", "/v1/options")

    # -- uploads ----------------------------------------------------------------------------

    def upload(self, path: str, kind: str, upload_id: Optional[str] = None,
               on_part: Optional[Callable[[int, int], None]] = None) -> str:
        """Uploads the file `path` as an input of `kind` (lidar, photos, colmap,
        control_points, field_dbh) in parts, and completes it; returns the upload's id.

        Resumable: with `upload_id` (an upload this key created for the same file) only the
        parts the server lacks are sent. A part that fails on a dropped connection or a 5xx is
        retried. The server checks the whole file's size and sha256 at completion and inspects
        its content (422 with the reason when it is unusable). `on_part(sent, total)` is
        called after each part.
        """
        size = os.path.getsize(path)
        if upload_id is None:
            created = self._json("POST", "/v1/uploads", {
                "kind": kind, "filename": os.path.basename(path), "size": size,
                "sha256": _sha256(path)})
            upload_id = created["id"]
            state = created
        else:
            state = self.upload_state(upload_id)
        part_size = int(state["part_size"])
        total = int(state["parts_total"])
        have = set(state.get("parts_received") or [])
        with open(path, "rb") as f:
            for n in range(total):
                if n in have:
                    continue
                f.seek(n * part_size)
                chunk = f.read(part_size)
                self._retrying(lambda: self._request(
                    "PUT", f"/v1/uploads/{upload_id}/parts/{n}", chunk,
                    {"Content-Type": "application/octet-stream"}))
                if on_part:
                    on_part(n + 1, total)
        self._json("POST", f"/v1/uploads/{upload_id}/complete")
        return upload_id

    def upload_state(self, upload_id: str) -> dict:
        """`GET /v1/uploads/{id}`: which parts and how many bytes have arrived."""
        return self._json("GET", f"/v1/uploads/{upload_id}")

    # -- jobs -------------------------------------------------------------------------------

    def submit(self, inputs: Dict[str, str], params: Optional[dict] = None,
               idempotency_key: Optional[str] = None, webhook: Optional[dict] = None) -> dict:
        """`POST /v1/jobs` over uploaded `inputs` (kind → upload id); the new job. The same
        `idempotency_key` always gives the same job."""
        body: Dict[str, Any] = {"inputs": inputs}
        if params is not None:
            body["params"] = params
        if webhook is not None:
            body["webhook"] = webhook
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else None
        return self._json("POST", "/v1/jobs", body, headers)

    def job(self, job_id: str) -> dict:
        """`GET /v1/jobs/{id}`: state, stages, progress, ETA and artifacts."""
        return self._json("GET", f"/v1/jobs/{job_id}")

    def results(self, job_id: str) -> dict:
        """`GET /v1/jobs/{id}/results`: every finished stage's report."""
        return self._json("GET", f"/v1/jobs/{job_id}/results")

    def cancel(self, job_id: str) -> dict:
        return self._json("POST", f"/v1/jobs/{job_id}/cancel")

    def retry(self, job_id: str, from_stage: Optional[str] = None) -> dict:
        return self._json("POST", f"/v1/jobs/{job_id}/retry",
                          {"from_stage": from_stage} if from_stage else {})

    def events(self, job_id: str) -> Iterator[Tuple[str, Any]]:
        """The job's server-sent events as (event, data) pairs, data parsed from JSON where it
        is JSON, until the server ends the stream (after the `end` event)."""
        resp = self._request("GET", f"/v1/jobs/{job_id}/events",
                             headers={"Accept": "text/event-stream"}, stream=True)
        with resp:
            event, data = "message", []
            for raw in resp:
                line = raw.decode("utf-8").rstrip("\r\n")
                if line == "":
                    if data:
                        text = "\n".join(data)
                        try:
                            yield event, json.loads(text)
                        except ValueError:
                            yield event, text
                    event, data = "message", []
                elif line.startswith(":"):
                    continue
                elif line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:"):
                    data.append(line[5:].lstrip(" "))

    def wait(self, job_id: str, on_event: Optional[Callable[[str, Any], None]] = None,
             timeout: Optional[float] = None) -> dict:
        """Follows the job's events until it ends (or `timeout` seconds pass: then
        TimeoutError); returns the job as it ended. A dropped stream is reopened."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                for event, data in self.events(job_id):
                    if on_event:
                        on_event(event, data)
                    if deadline is not None and time.monotonic() > deadline:
                        raise TimeoutError(f"job {job_id} still running after {timeout} s")
            except (urllib.error.URLError, ConnectionError):
                pass
            job = self.job(job_id)
            if job["state"] in TERMINAL:
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['state']} after {timeout} s")
            time.sleep(0.5)

    # -- downloads --------------------------------------------------------------------------

    def download(self, job_id: str, name: str, dest: str) -> str:
        """Downloads the artifact `name` (as the job lists it, e.g. `export/splats.glb`) to the
        file `dest`, checks its sha256 against the listing, and returns `dest`. Written to a
        temporary file first, so `dest` is never left half written."""
        listed = {a["name"]: a for a in self.job(job_id).get("artifacts", [])}
        if name not in listed:
            raise NotFound(404, "Not Found", f"job {job_id} has no artifact {name}")
        want = listed[name].get("sha256")
        quoted = urllib.parse.quote(name)

        def fetch() -> str:
            h = hashlib.sha256()
            tmp = f"{dest}.part"
            with self._request("GET", f"/v1/jobs/{job_id}/artifacts/{quoted}",
                               stream=True) as resp, open(tmp, "wb") as out:
                for block in iter(lambda: resp.read(1 << 20), b""):
                    h.update(block)
                    out.write(block)
            if want and h.hexdigest() != want:
                os.remove(tmp)
                raise ChecksumMismatch(0, "Checksum mismatch",
                                       f"{name}: sha256 {h.hexdigest()}, listed {want}")
            os.replace(tmp, dest)
            return dest

        return self._retrying(fetch)

    def trees_csv(self, job_id: str) -> str:
        """`GET /v1/jobs/{id}/trees.csv`: the inventory as CSV text."""
        _, raw = self._request("GET", f"/v1/jobs/{job_id}/trees.csv")
        return raw.decode("utf-8")
