"""The keypoint editor as a local web page (``kpd view --browser``): a standard-library HTTP server and a three.js page.

The server sends the page (``viewer/web``), three.js (copied into ``viewer/web/vendor`` by ``make web`` from the npm
package pinned in ``package-lock.json``) and the shape's rig as a GLB (:mod:`kpd.morph`): the mesh with the rig's
(V, K) basis as vertex attributes (``_KPD_BASIS_<j>``), or with ``?morph=three`` its keypoint morph targets. The page
draws on the viewer's own GPU: a keypoint dragged with the mouse sets the keypoints' offsets ``o_i``, and the vertex
shader adds ``sum_i B_i o_i`` (or three.js's morph targets do), so the mesh follows every frame without a round trip
to the server. Every edit the page offers (a keypoint's move, the same move through the category prior, the
principal components' sliders) is a sum of targets whose keypoint offsets the GLB carries in ``asset.extras.kpd``;
the page keeps the weights of those targets, and "save" sends them back, where
:meth:`kpd.morph.MorphRig.vertices_at` makes the mesh (in float64, the rig's own edit) and
:func:`kpd.io.write_mesh` writes it through kpd's one atomic writer.

Nothing leaves the machine: the server binds to localhost unless told otherwise, the page loads nothing from the
network, and an SSH port forward (``ssh -L 8765:localhost:8765 server``) brings it to a remote user's browser.

The server obeys only the page it printed, as Jupyter's does (docs/editor.md, "What the browser editor trusts"):
every request names a random secret of this launch as the first segment of its path (``/<secret>/``: the page's
relative URLs, its stylesheet, its module scripts and three.js's own imports carry it with no cookie, which the
browser would also send to every other server on localhost); the page's requests of the rig, its info and the
save also carry it in an ``Authorization: Bearer`` header, which no form and no cross-site ``no-cors`` request can
set; the ``Host`` header must name this machine (DNS rebinding), a save must come from the server's own ``Origin``
as ``application/json``; a request must arrive whole within ``timeout`` seconds and at most :data:`MAX_BODY`
bytes, at most :data:`MAX_CONNECTIONS` connections are served at once, and every refusal is a 4xx JSON answer.
"""

from __future__ import annotations

import contextlib
import errno
import hmac
import http.server
import io
import ipaddress
import json
import logging
import math
import mimetypes
import re
import secrets
import socket
import sys
import threading
import time
from collections.abc import Sequence
from http import HTTPStatus
from pathlib import Path
from typing import Any

import numpy as np

from kpd.errors import InputError, KpdError, WriteError

__all__ = ["MAX_BODY", "MAX_CONNECTIONS", "WEB_ROOT", "BrowserEditor", "page_files_missing", "save_weights"]

log = logging.getLogger(__name__)

WEB_ROOT = Path(__file__).resolve().parent / "web"
_VENDOR = WEB_ROOT / "vendor" / "three"
_PAGE_FILES = ("index.html", "app.js", "style.css")
_VENDOR_FILES = ("build/three.module.js", "build/three.core.js", "examples/jsm/loaders/GLTFLoader.js",
                 "examples/jsm/controls/OrbitControls.js")
MAX_BODY = 1 << 20  # a save request is a few kilobytes of weights
MAX_CONNECTIONS = 32  # a page opens six at once; more are answered 503 at once, without a thread
_API = ("/info.json", "/rig.glb", "/save")  # what only the page's script asks for: the secret also in a header
_HOST = re.compile(r"(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)(?::[0-9]{1,5})?")  # a Host header: name[:port]
_WILDCARDS = ("", "0.0.0.0", "::")


def page_files_missing() -> list[str]:
    """The files the page needs that are not installed (three.js comes from ``make web``)."""
    return [str(WEB_ROOT / f) for f in _PAGE_FILES if not (WEB_ROOT / f).is_file()] + \
        [str(_VENDOR / f) for f in _VENDOR_FILES if not (_VENDOR / f).is_file()]


class BrowserEditor:
    """A local web server for one rig: the page, three.js, the rig's GLB, and "save mesh".

    It listens as soon as it is made (a port in use is refused before any work); :meth:`show` gives it the rig.

    Parameters
    ----------
    out : where "save mesh" writes (a mesh format of :func:`kpd.io.write_mesh`), or None (the page's save is off).
    force : let the first save replace an existing ``out`` (later saves replace what this editor wrote).
    inputs : the command's input files, never replaced.
    host, port : where to listen (port 0: a free port).
    timeout : seconds within which a request (its headers and body) must arrive whole, and a send must progress.

    Attributes
    ----------
    secret : this launch's secret (:func:`secrets.token_urlsafe`, 256 bits), part of :attr:`url`.
    """

    def __init__(self, *, out: str | Path | None = None, force: bool = False, inputs: tuple = (),
                 host: str = "127.0.0.1", port: int = 8765, timeout: float = 10.0) -> None:
        missing = page_files_missing()
        if missing:
            raise InputError(f"the browser page's files are not installed ({missing[0]} is missing); run make web "
                             "(npm ci copies three.js into the package)")
        self.out = None if out is None else Path(out)
        self.force = force
        self.inputs = inputs
        self.morph = None
        self.name = "shape"
        self.prior_on = False
        self.camera = {"azimuth": 30.0, "elevation": 20.0}
        self.glb = None  # the page's GLB (the basis as vertex attributes): a temporary file without a name (show)
        self.glb_size = 0
        self._targets = None  # (file, size) of the GLB with keypoint targets, once asked for
        self._settings: dict = {}
        self._saved = False
        self._lock = threading.Lock()
        self._targets_lock = threading.Lock()
        self.secret = secrets.token_urlsafe(32)
        self.timeout = float(timeout)
        # the page's files, found once: a request's path is looked up here and never reaches the file system
        self._files = {"/" + f.relative_to(WEB_ROOT).as_posix(): f for f in sorted(WEB_ROOT.rglob("*")) if f.is_file()}
        self._files["/"] = WEB_ROOT / "index.html"
        try:
            self.server = _Server((host, port), _handler(self), connections=MAX_CONNECTIONS)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InputError(f"--port {port}: the port is in use on {host}; choose another --port (0 picks a "
                                 "free one)") from None
            raise InputError(f"--host {host} --port {port}: cannot listen there ({exc.strerror or exc})") from None
        bound = str(self.server.server_address[0])
        # the names a browser may use for this server (its Host header): any name of this machine's loopback, the
        # name --host gave, and for a wildcard address the machine's own names and any IP address (a literal
        # address cannot be rebound by DNS)
        self._names = {"localhost", str(host).lower().strip("[]"), bound.lower()}
        self._any_address = str(host) in _WILDCARDS
        if self._any_address:
            self._names |= {socket.gethostname().lower(), socket.getfqdn().lower()}

    def show(self, morph: Any, *, name: str = "shape", up: str = "+z", prior: bool = False, azimuth: float = 30.0,
             elevation: float = 20.0) -> None:
        """Serve ``morph`` (a :class:`kpd.morph.MorphRig`) under ``name``, its ``up`` axis turned to the page's up;
        ``prior``: start with the prior switch on; ``azimuth``, ``elevation``: the camera's start, in degrees."""
        # every edit is a sum of keypoint offsets, so the page needs the basis (K numbers a vertex, as vertex
        # attributes) and asset.extras.kpd's offsets; the keypoint targets (9 K numbers a vertex) are made only if
        # asked for (?morph=three)
        self._settings = {"name": name, "up": up}
        glb, size = self._written(morph, targets=[], basis=True, stand_in=_stand_in)
        self.close()
        self.glb, self.glb_size = glb, size
        self.morph, self.name, self.prior_on = morph, name, bool(prior)
        self.camera = {"azimuth": float(azimuth), "elevation": float(elevation)}

    def _written(self, morph: Any, **kwargs) -> tuple[Any, int]:
        """A GLB of ``morph`` in a temporary file without a name (hundreds of megabytes for a scan: not held in
        memory, and gone with the process however it ends) and its length."""
        import tempfile

        from kpd.io.atomic import describe_os_error
        from kpd.morph import write_glb_to

        try:
            glb = tempfile.TemporaryFile(prefix="kpd-page-")
            try:
                size = write_glb_to(glb, morph, **self._settings, **kwargs)
                glb.flush()
            except BaseException:
                glb.close()
                raise
        except OSError as exc:
            raise WriteError(describe_os_error(exc, f"the page's rig in {tempfile.gettempdir()}") +
                             " (TMPDIR chooses the folder)") from None
        return glb, size

    def targets_glb(self) -> tuple[Any, int]:
        """The GLB with the keypoint targets (three.js's own morph targets: ``?morph=three``), made on first use."""
        with self._targets_lock:
            if self._targets is None:
                morph = self.morph
                self._targets = self._written(morph, targets=[n for n in morph.names if n.startswith("keypoint_")])
            return self._targets

    @property
    def url(self) -> str:
        """The page's address, with this launch's secret (for a wildcard --host, at this machine's name)."""
        host, port = self.server.server_address[:2]
        host = socket.gethostname() if self._any_address else host
        shown = f"[{host}]" if ":" in str(host) else host
        return f"http://{shown}:{port}/{self.secret}/"

    @property
    def exposed(self) -> bool:
        """Whether the server listens on an address other machines may reach (not a loopback address)."""
        return not ipaddress.ip_address(str(self.server.server_address[0]).split("%")[0]).is_loopback

    def allows_host(self, header: str | None) -> bool:
        """Whether a request's ``Host`` header names this server (its port is not checked: an SSH forward may
        change it); a page of another name that DNS resolves here (DNS rebinding) is refused."""
        match = _HOST.fullmatch(header or "")
        if match is None:
            return False
        name = match.group(1).lower().strip("[]")
        if name in self._names:
            return True
        try:
            address = ipaddress.ip_address(name)
        except ValueError:
            return False
        return address.is_loopback or self._any_address

    def has_secret(self, value: str) -> bool:
        """Whether ``value`` is this launch's secret (compared in constant time)."""
        return hmac.compare_digest(value.encode("utf-8", "surrogateescape"), self.secret.encode("ascii"))

    def serve_forever(self) -> None:
        """Serve until :meth:`shutdown` (another thread) or Ctrl+C."""
        try:
            self.server.serve_forever(poll_interval=0.2)
        finally:
            self.server.server_close()

    def shutdown(self) -> None:
        self.server.shutdown()

    def close(self) -> None:
        """Let go of the rig's GLBs (the server stays)."""
        if self.glb is not None:
            self.glb.close()
            self.glb, self.glb_size = None, 0
        with self._targets_lock:
            if self._targets is not None:
                self._targets[0].close()
                self._targets = None

    # --- what the page asks for ---------------------------------------------------------------------------------

    def info(self) -> dict:
        return {"name": self.name, "out": None if self.out is None else str(self.out), "prior": self.prior_on,
                "keypoints": 0 if self.morph is None else len(self.morph.keypoints), **self.camera}

    def save(self, weights: dict) -> str:
        """Write the mesh of ``{target: weight}`` to ``out``; returns the message the page shows."""
        from kpd.io import Outputs, mesh_companions, write_mesh

        if self.out is None:
            raise InputError("no output file: start kpd view with --out FILE to save the edited mesh")
        if self.morph is None:
            raise InputError("no rig is shown yet")
        with np.errstate(over="ignore", invalid="ignore"):
            vertices = self.morph.vertices_at(weights)
            # a mesh file holds float32 (glTF) or text the readers take as such
            if not np.isfinite(vertices).all() or np.abs(vertices).max() > np.finfo(np.float32).max:
                raise InputError("the edit moves the mesh beyond the numbers a mesh file holds; undo it")
        mesh = self.morph.mesh.with_vertices(vertices)
        with self._lock:
            # the first save may not replace a file without --force; later ones replace what this editor wrote
            with Outputs(force=self.force or self._saved, inputs=self.inputs) as outputs:
                out = outputs.file(self.out, "--out", what="mesh")
                outputs.companions(out, mesh_companions(out, mesh))
                write_mesh(outputs.stage(out), mesh)
            self._saved = True
        log.info("saved %s", self.out)
        return f"saved {self.out} ({len(mesh.vertices)} vertices)"


def _stand_in(vertices, triangles):
    """The triangles of a large primitive's coarse stand-in over its own vertices (the window editor's: vertices
    clustered on a grid, one kept per cell), which a page without a GPU draws while a keypoint is dragged; None for
    a primitive of at most :data:`kpd.viewer.gl.PROXY_TRIANGLES` triangles."""
    from kpd.viewer.gl import PROXY_TRIANGLES, proxy_triangles

    found = proxy_triangles(vertices, triangles, PROXY_TRIANGLES)
    return None if found is None else found[0][found[1]]


def save_weights(body: bytes, names: Sequence[str]) -> dict[str, float]:
    """The weights of a save request's body, ``{"weights": {target: weight}}``, checked strictly.

    Parameters
    ----------
    body : the request's bytes (UTF-8 JSON).
    names : (T,) the rig's target names.

    Returns
    -------
    ``{target: weight}``: known targets, each once, with finite numbers. Anything else is an :class:`InputError`:
    other JSON (``null``, strings, booleans, lists, other keys), numbers that are not finite as float64 (``NaN``,
    ``Infinity``, or an integer of 400 digits, which is read as a float and so is never a huge int), and nesting so
    deep that the parser gives up (100,000 ``[``).
    """

    def unique(pairs: list) -> dict:
        keys = [key for key, _ in pairs]
        if len(set(keys)) != len(keys):
            raise ValueError("a key is given twice")
        return dict(pairs)

    def refuse(constant: str) -> float:
        raise ValueError(f"{constant} is not a number")

    try:
        value = json.loads(body.decode("utf-8"), parse_int=float, parse_float=float, parse_constant=refuse,
                           object_pairs_hook=unique)
    except RecursionError:
        raise InputError("a save request is {\"weights\": {target: weight}}; got JSON nested too deep") from None
    except ValueError as exc:  # not UTF-8, not JSON, a key twice, NaN or Infinity
        raise InputError(f"a save request must be JSON: {' '.join(str(exc).split())[:200]}") from None
    if not isinstance(value, dict) or set(value) != {"weights"} or not isinstance(value["weights"], dict):
        raise InputError("a save request is {\"weights\": {target: weight}}")
    known = set(names)
    for name, weight in value["weights"].items():
        if name not in known:
            raise InputError(f"unknown morph target {name[:60]!r}; targets are keypoint_<i>_<axis>, "
                             f"prior_<i>_<axis>, pca_<c> (this rig has {len(names)})")
        if not isinstance(weight, float) or not math.isfinite(weight):
            got = ("null" if weight is None else "true or false" if isinstance(weight, bool) else "a string" if
                   isinstance(weight, str) else "a list" if isinstance(weight, list) else "an object" if
                   isinstance(weight, dict) else "a number beyond float64's range")
            raise InputError(f"the weight of {name} must be a finite number; got {got}")
    return value["weights"]


class _Refused(Exception):
    """A request the editor answers with ``status`` and a JSON ``{"ok": false, "message": ...}``."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


class _Server(http.server.ThreadingHTTPServer):
    """http.server's threads, at most ``connections`` at once: a connection beyond them is answered 503 at once by
    the accepting thread, so no number of connections that never finish their request (slowloris) exhausts the
    threads or memory; each of those is cut at the editor's timeout (:class:`_Arrival`)."""

    daemon_threads = True
    request_queue_size = 64

    def __init__(self, address: tuple, handler: type, *, connections: int) -> None:
        self.address_family = socket.AF_INET6 if ":" in str(address[0]) else socket.AF_INET
        self.slots = threading.BoundedSemaphore(connections)
        super().__init__(address, handler)

    def process_request(self, request, client_address) -> None:
        if not self.slots.acquire(blocking=False):
            body = json.dumps({"ok": False, "message": "the editor is busy; try again"}).encode()
            try:
                request.setblocking(False)
                with contextlib.suppress(BlockingIOError):  # what came already: unread, it would reset the answer
                    request.recv(1 << 16)
                request.settimeout(1.0)
                request.sendall(b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                                b"Connection: close\r\nContent-Length: %d\r\n\r\n%s" % (len(body), body))
            except OSError:
                pass
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()

    def handle_error(self, request, client_address) -> None:
        # a connection that broke (reset, timed out): the log's, never a traceback on the user's terminal
        log.debug("the connection from %s ended in an error", client_address, exc_info=sys.exc_info())


class _Arrival(io.RawIOBase):
    """A connection's incoming bytes, which must arrive before ``deadline`` (time.monotonic): a client that sends
    its request a byte now and then holds its thread no longer than the editor's timeout."""

    def __init__(self, connection: socket.socket) -> None:
        self.connection = connection
        self.deadline = math.inf

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the request did not arrive in time")
        self.connection.settimeout(left)
        return self.connection.recv_into(buffer)


def _handler(editor: BrowserEditor):
    class Handler(http.server.BaseHTTPRequestHandler):
        server_version = "kpd"
        # HTTP/1.0: one request a connection, so no idle connection waits for a next one

        def setup(self) -> None:
            super().setup()
            self.rfile.close()
            self.rfile = io.BufferedReader(_Arrival(self.connection))
            self._body_read = False
            self._answered = False

        def handle_one_request(self) -> None:
            self.rfile.raw.deadline = time.monotonic() + editor.timeout
            super().handle_one_request()

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the base class's name)
            # the log (kpd -v) may be kept or shared: the secret is not written into it
            log.debug("%s %s", self.address_string(), (format % args).replace(editor.secret, "SECRET"))

        def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
            # http.server's own refusals (a request line or headers too long or malformed, a method without a
            # do_ method): JSON as the editor's own; a method it does not offer (405) and an HTTP version it does not
            # speak (400) are the client's mistakes, answered as such
            code = {HTTPStatus.NOT_IMPLEMENTED: HTTPStatus.METHOD_NOT_ALLOWED,
                    HTTPStatus.HTTP_VERSION_NOT_SUPPORTED: HTTPStatus.BAD_REQUEST}.get(code, code)
            self.close_connection = True
            self._json(code, {"ok": False, "message": message or HTTPStatus(code).phrase})

        def _start(self, status: int, kind: str, size: int, extra: tuple = ()) -> None:
            self._answered = True
            self.connection.settimeout(editor.timeout)  # a send that does not progress in time fails
            self.request_version = "HTTP/1.0"  # never HTTP/0.9's bare body: every answer has its status and type
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(size))
            self.send_header("Cache-Control", "no-store")
            # nothing of the editor is shown in another site's frame, read by another origin's no-cors request,
            # sniffed as another type, or named in a Referer
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("X-Frame-Options", "DENY")
            self.send_header("Cross-Origin-Resource-Policy", "same-origin")
            self.send_header("Referrer-Policy", "no-referrer")
            for name, value in extra:
                self.send_header(name, value)
            self.end_headers()

        def _send(self, status: int, body: bytes, kind: str, extra: tuple = ()) -> None:
            self._start(status, kind, len(body), extra)
            if self.command != "HEAD":
                self.wfile.write(body)

        def _send_file(self, fh, size: int, kind: str) -> None:
            """Send ``size`` bytes of ``fh`` from its start, by the kernel (sendfile at an offset of this request's
            own: requests at once do not move each other's place)."""
            self._start(200, kind, size)
            self.wfile.flush()
            self.connection.sendfile(fh, 0, size)

        def _json(self, status: int, value: dict) -> None:
            self._send(status, json.dumps(value).encode("utf-8"), "application/json")

        # --- every request: the checks, then the route; every refusal a JSON answer ----------------------------

        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            self._answer(self._get)

        def do_POST(self) -> None:  # noqa: N802
            self._answer(self._post)

        def do_HEAD(self) -> None:  # noqa: N802
            self.send_error(HTTPStatus.METHOD_NOT_ALLOWED)

        do_OPTIONS = do_PUT = do_DELETE = do_PATCH = do_HEAD  # a cross-origin preflight is refused too

        def _answer(self, route) -> None:
            try:
                if not editor.allows_host(self.headers.get("Host")):
                    raise _Refused(HTTPStatus.MISDIRECTED_REQUEST, "this server answers only to the address "
                                   "kpd view printed (localhost or the --host name)")
                path, _, query = self.path.partition("?")
                secret, slash, rest = path[1:].partition("/")
                if not (path.startswith("/") and editor.has_secret(secret)):
                    raise _Refused(HTTPStatus.FORBIDDEN, "open the address kpd view printed: it carries this "
                                   "launch's secret")
                if not slash:  # /<secret>: the page's own relative URLs need the folder's slash
                    return self._send(HTTPStatus.MOVED_PERMANENTLY, b"", "text/plain",
                                      (("Location", f"/{secret}/"),))
                rest = "/" + rest
                # a browser names the page that asks (Origin: on every POST and on a cross-origin fetch; and
                # Sec-Fetch-Site): only the editor's own page, or the user's own typing, is served
                origin = self.headers.get("Origin")
                if (origin is None and self.command == "POST") or (
                        origin is not None and origin.lower() != f"http://{self.headers['Host']}".lower()):
                    raise _Refused(HTTPStatus.FORBIDDEN, f"only the editor's own page may ask this; got Origin "
                                   f"{(origin or '')[:100]!r}")
                if self.headers.get("Sec-Fetch-Site", "none") not in ("same-origin", "none"):
                    raise _Refused(HTTPStatus.FORBIDDEN, "only the editor's own page may ask this")
                if rest in _API:
                    kind, _, token = self.headers.get("Authorization", "").partition(" ")
                    if kind.lower() != "bearer" or not editor.has_secret(token.strip()):
                        raise _Refused(HTTPStatus.FORBIDDEN, f"{rest} is for the editor's page only")
                route(rest, query)
            except _Refused as refusal:
                self._refuse(refusal.status, str(refusal))
            except KpdError as exc:
                self._refuse(HTTPStatus.BAD_REQUEST if isinstance(exc, InputError) else
                             HTTPStatus.INTERNAL_SERVER_ERROR, " ".join(str(exc).split()))
            except (ConnectionError, TimeoutError):  # the page went away, or stopped reading
                self.close_connection = True
            except Exception as exc:  # a server answers every request; the fault goes to the log
                log.error("the browser editor failed on %s %s: %s", self.command, self.path[:200], exc)
                log.debug("the failure", exc_info=True)
                self._refuse(HTTPStatus.INTERNAL_SERVER_ERROR, f"the editor failed: {exc}")

        def _refuse(self, status: int, message: str) -> None:
            self.close_connection = True
            if self._answered:  # the answer had begun: the connection's end is all that is left to say
                return
            if self.command == "POST" and not self._body_read:
                self._discard_body()
            try:
                self._json(status, {"ok": False, "message": message})
            except (ConnectionError, TimeoutError):
                pass

        def _discard_body(self) -> None:
            """Read a refused POST's body (up to MAX_BODY): closing a socket with unread bytes resets it, and the
            client would see a broken connection instead of the answer."""
            try:
                length = int(self.headers.get("Content-Length", "0"))
                if 0 < length <= MAX_BODY:
                    self.rfile.read(length)
            except (ValueError, ConnectionError, TimeoutError):
                pass

        def _get(self, path: str, query: str) -> None:
            if path == "/rig.glb":
                if editor.morph is None:
                    raise _Refused(HTTPStatus.SERVICE_UNAVAILABLE, "the rig is not ready")
                if query == "morph=three":
                    return self._send_file(*editor.targets_glb(), "model/gltf-binary")
                return self._send_file(editor.glb, editor.glb_size, "model/gltf-binary")
            if path == "/info.json":
                return self._json(200, editor.info())
            file = editor._files.get(path)
            if file is None:  # only the page's own files, looked up by name: no path reaches the file system
                raise _Refused(HTTPStatus.NOT_FOUND, "not found")
            kind = "text/javascript" if file.suffix == ".js" else mimetypes.guess_type(file.name)[0] or "text/plain"
            self._send(200, file.read_bytes(), kind)

        def _post(self, path: str, query: str) -> None:
            if path != "/save":
                raise _Refused(HTTPStatus.NOT_FOUND, "not found")
            kind = self.headers.get("Content-Type", "").split(";")[0].strip().lower()
            if kind != "application/json":  # a form or a no-cors request cannot send this type
                raise _Refused(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, f"a save is application/json; got {kind[:60]!r}")
            if "Transfer-Encoding" in self.headers:
                raise _Refused(HTTPStatus.LENGTH_REQUIRED, "a save gives its Content-Length")
            text = self.headers.get("Content-Length")
            if text is None:
                raise _Refused(HTTPStatus.LENGTH_REQUIRED, "a save gives its Content-Length")
            text = text.strip()
            if not re.fullmatch(r"[0-9]+", text):
                raise _Refused(HTTPStatus.BAD_REQUEST, f"Content-Length must be a number; got {text[:40]!r}")
            if len(text) > 12 or int(text) > MAX_BODY:
                self._body_read = True  # left unread: too long to take
                raise _Refused(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"a save request carries at most {MAX_BODY} "
                               f"bytes; got {text[:20]}")
            length = int(text)
            try:
                body = self.rfile.read(length)
            except TimeoutError:
                self._body_read = True
                raise _Refused(HTTPStatus.REQUEST_TIMEOUT, "the save request did not arrive in time") from None
            self._body_read = True
            if len(body) < length:
                raise _Refused(HTTPStatus.BAD_REQUEST, f"the save request ended after {len(body)} of {length} bytes")
            if editor.morph is None:
                raise InputError("no rig is shown yet")
            message = editor.save(save_weights(body, editor.morph.names))
            self._json(200, {"ok": True, "message": message})

    return Handler
