"""A minimal asyncio HTTP/1.1 client: one keep-alive connection, one request at a time.

The simulated clients, the driver and ``wallcull loadtest --requests`` send thousands of small
requests a second. ``httpx.AsyncClient`` spends a few hundred microseconds of Python per request,
which on a 2-core machine shared with the server would measure the client rather than the
server. This speaks just enough HTTP/1.1 for the wallcull API: ``Content-Length`` and chunked
bodies, keep-alive, no pipelining, one transparent reconnect when the server closed an idle
connection before answering. ``https://`` goes over TLS, checked against the system's
certificate authorities (``SSL_CERT_FILE`` names others, as for every Python client).
"""

from __future__ import annotations

import asyncio
import json
import ssl
from dataclasses import dataclass
from urllib.parse import urlsplit

import msgpack

MSGPACK = "application/msgpack"


class HTTPError(Exception):
    """A response with an unexpected status (carries it and the server's ``detail``)."""

    def __init__(self, status: int, detail: str, method: str = "", target: str = ""):
        super().__init__(f"{method} {target}: HTTP {status}: {detail}".strip())
        self.status, self.detail = status, detail


class Untrusted(ValueError):
    """An ``https://`` server whose certificate the client does not trust."""


@dataclass
class Response:
    status: int
    headers: dict[str, str]  # lower-case names
    body: bytes

    def data(self):
        """The body decoded by its content type (msgpack or JSON; ``None`` when empty)."""
        if not self.body:
            return None
        if self.headers.get("content-type", "").startswith(MSGPACK):
            return msgpack.unpackb(self.body, raw=False)
        return json.loads(self.body)

    def detail(self) -> str:
        try:
            data = self.data()
        except Exception:  # noqa: BLE001 - an error body that is not JSON: show it raw
            return self.body[:200].decode("latin-1")
        return str(data.get("detail", data)) if isinstance(data, dict) else str(data)


def split_url(url: str) -> tuple[str, int, str, bool]:
    """``(host, port, path prefix, tls)`` of an ``http://`` or ``https://`` URL."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https"):
        raise ValueError(f"only http:// and https:// URLs are supported, got {url!r}")
    tls = parts.scheme == "https"
    return parts.hostname or "127.0.0.1", parts.port or (443 if tls else 80), \
        parts.path.rstrip("/"), tls


class Connection:
    """One keep-alive HTTP/1.1 connection to ``base_url``. Not safe for concurrent requests:
    give each task its own (that is what a render node's single socket would be)."""

    def __init__(self, base_url: str, token: str | None = None, timeout: float | None = 30.0):
        self.host, self.port, self.prefix, self.tls = split_url(base_url)
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.timeout = timeout
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._host_header = f"{self.host}:{self.port}"
        self.requests = 0
        self.bytes_in = 0

    async def _connect(self) -> None:
        try:
            self._reader, self._writer = await asyncio.open_connection(
                self.host, self.port, ssl=ssl.create_default_context() if self.tls else None)
        except ssl.SSLCertVerificationError as exc:  # no retry mends it: not an OSError here
            raise Untrusted(f"{self.base_url}: the server's certificate is not trusted "
                            f"({exc.verify_message}); SSL_CERT_FILE names a file of "
                            f"certificates to trust") from None

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            try:
                await self._writer.wait_closed()
            except (ConnectionError, OSError):
                pass
        self._reader = self._writer = None

    async def request(self, method: str, target: str, body: bytes = b"",
                      content_type: str | None = None, accept: str = MSGPACK,
                      headers: dict | None = None, auth: bool = False) -> Response:
        """Send one request and read its response. ``target`` is the path and query."""
        lines = [f"{method} {self.prefix}{target} HTTP/1.1", f"host: {self._host_header}",
                 f"accept: {accept}"]
        if body or method in ("POST", "PUT", "PATCH"):
            lines.append(f"content-length: {len(body)}")
            if content_type:
                lines.append(f"content-type: {content_type}")
        if auth and self.token:
            lines.append(f"authorization: Bearer {self.token}")
        for k, v in (headers or {}).items():
            lines.append(f"{k}: {v}")
        head = ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")
        for attempt in (0, 1):
            fresh = self._writer is None
            if fresh:
                await self._connect()
            try:
                self._writer.write(head + body if body else head)
                coro = self._read_response(method)
                return await (asyncio.wait_for(coro, self.timeout) if self.timeout else coro)
            except (ConnectionError, asyncio.IncompleteReadError, EOFError) as exc:
                # A keep-alive connection the server closed while idle fails on first use:
                # retry once on a new one. A fresh connection that fails is a real error.
                await self.close()
                if fresh or attempt:
                    raise ConnectionError(f"{method} {target}: {exc!r}") from exc
            except BaseException:
                await self.close()  # a half-read response leaves the stream unusable
                raise
        raise AssertionError("unreachable")

    async def _read_response(self, method: str) -> Response:
        reader = self._reader
        while True:
            raw = await reader.readuntil(b"\r\n\r\n")
            status_line, *header_lines = raw[:-4].decode("latin-1").split("\r\n")
            status = int(status_line.split(" ", 2)[1])
            if status >= 200 or status == 101:
                break  # skip 1xx interim responses
        headers = {}
        for line in header_lines:
            name, _, value = line.partition(":")
            headers[name.strip().lower()] = value.strip()
        if method == "HEAD" or status in (204, 304) or 100 <= status < 200:
            body = b""
        elif "content-length" in headers:
            body = await reader.readexactly(int(headers["content-length"]))
        elif headers.get("transfer-encoding", "").lower() == "chunked":
            parts = []
            while True:
                size = int((await reader.readuntil(b"\r\n"))[:-2].split(b";")[0], 16)
                if size == 0:
                    await reader.readuntil(b"\r\n")  # no trailers expected
                    break
                parts.append(await reader.readexactly(size))
                await reader.readexactly(2)
            body = b"".join(parts)
        else:
            body = await reader.read()
            headers["connection"] = "close"
        if headers.get("connection", "").lower() == "close":
            await self.close()
        self.requests += 1
        self.bytes_in += len(body)
        return Response(status, headers, body)

    # ---------------------------------------------------------------- conveniences

    async def call(self, method: str, target: str, payload=None, *, expect=(200, 201, 204),
                   auth: bool = False, body_format: str = "json"):
        """A request with a JSON (or msgpack) body; returns the decoded answer, raises
        :class:`HTTPError` on an unexpected status."""
        body, ctype = b"", None
        if payload is not None:
            if body_format == "msgpack":
                body, ctype = msgpack.packb(payload, use_bin_type=True), MSGPACK
            else:
                body, ctype = json.dumps(payload, separators=(",", ":")).encode(), "application/json"
        r = await self.request(method, target, body, ctype, auth=auth)
        if r.status not in expect:
            raise HTTPError(r.status, r.detail(), method, target)
        return r.data()

    async def wall_deleted(self, wid: str) -> bool:
        """Whether the server says wall ``wid`` is gone: ``GET /walls/{wid}``, which needs no
        token, answers 404 (a deleted wall's credentials are refused 401, and so are asked
        after this way). False when the server does not answer: the wall may come back with
        it."""
        try:
            r = await self.request("GET", f"/walls/{wid}")
        except (ConnectionError, OSError, asyncio.TimeoutError):
            return False
        return r.status == 404

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc):
        await self.close()


def run(coro):
    """Run on uvloop when it is installed, as uvicorn does for the server: less CPU per
    socket event, which counts with a whole wall of nodes in one process."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)
