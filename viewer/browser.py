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
"""

from __future__ import annotations

import errno
import http.server
import json
import logging
import mimetypes
import os
import threading
from pathlib import Path
from typing import Any

from kpd.errors import InputError, KpdError, WriteError

__all__ = ["BrowserEditor", "WEB_ROOT", "page_files_missing"]

log = logging.getLogger(__name__)

WEB_ROOT = Path(__file__).resolve().parent / "web"
_VENDOR = WEB_ROOT / "vendor" / "three"
_PAGE_FILES = ("index.html", "app.js", "style.css")
_VENDOR_FILES = ("build/three.module.js", "build/three.core.js", "examples/jsm/loaders/GLTFLoader.js",
                 "examples/jsm/controls/OrbitControls.js")
_MAX_BODY = 1 << 20  # a save request is a few kilobytes of weights


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
    """

    def __init__(self, *, out: str | Path | None = None, force: bool = False, inputs: tuple = (),
                 host: str = "127.0.0.1", port: int = 8765) -> None:
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
        try:
            self.server = http.server.ThreadingHTTPServer((host, port), _handler(self))
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise InputError(f"--port {port}: the port is in use on {host}; choose another --port (0 picks a "
                                 "free one)") from None
            raise InputError(f"--host {host} --port {port}: cannot listen there ({exc.strerror or exc})") from None
        self.server.daemon_threads = True

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
        host, port = self.server.server_address[:2]
        shown = f"[{host}]" if ":" in str(host) else host
        return f"http://{shown}:{port}/"

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
        mesh = self.morph.mesh.with_vertices(self.morph.vertices_at(weights))
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


def _handler(editor: BrowserEditor):
    class Handler(http.server.BaseHTTPRequestHandler):
        server_version = "kpd"

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (the base class's name)
            log.debug("%s " + format, self.address_string(), *args)

        def _send(self, status: int, body: bytes, kind: str) -> None:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _send_file(self, fh, size: int, kind: str) -> None:
            """Send ``size`` bytes of ``fh`` from its start, by the kernel (os.sendfile at an offset of this
            request's own: requests at once do not move each other's place)."""
            self.send_response(200)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(size))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.flush()
            sent = 0
            try:
                while sent < size:
                    n = os.sendfile(self.connection.fileno(), fh.fileno(), sent, min(size - sent, 1 << 24))
                    if n == 0:
                        break
                    sent += n
            except (BrokenPipeError, ConnectionResetError):  # the page was closed or reloaded meanwhile
                self.close_connection = True

        def _json(self, status: int, value: dict) -> None:
            self._send(status, json.dumps(value).encode("utf-8"), "application/json")

        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            path, _, query = self.path.partition("?")
            if path == "/rig.glb":
                if editor.morph is None:
                    return self._send(503, b"the rig is not ready", "text/plain")
                if query == "morph=three":
                    try:
                        return self._send_file(*editor.targets_glb(), "model/gltf-binary")
                    except KpdError as exc:
                        return self._send(500, str(exc).encode("utf-8"), "text/plain")
                return self._send_file(editor.glb, editor.glb_size, "model/gltf-binary")
            if path == "/info.json":
                return self._json(200, editor.info())
            name = "index.html" if path == "/" else path.lstrip("/")
            file = (WEB_ROOT / name).resolve()
            if WEB_ROOT not in file.parents or not file.is_file():  # nothing outside the page's folder
                return self._send(404, b"not found", "text/plain")
            kind = "text/javascript" if file.suffix == ".js" else mimetypes.guess_type(file.name)[0] or "text/plain"
            self._send(200, file.read_bytes(), kind)

        def do_POST(self) -> None:  # noqa: N802
            if self.path != "/save":
                return self._send(404, b"not found", "text/plain")
            try:
                length = int(self.headers.get("Content-Length", "0"))
                if not 0 < length <= _MAX_BODY:
                    raise InputError(f"a save request must carry 1 byte to 1 MiB of JSON; got {length} bytes")
                body = json.loads(self.rfile.read(length))
                if not isinstance(body, dict) or not isinstance(body.get("weights"), dict):
                    raise InputError("a save request is {\"weights\": {target: weight}}")
                message = editor.save(body["weights"])
            except (KpdError, ValueError) as exc:
                return self._json(400, {"ok": False, "message": " ".join(str(exc).split())})
            self._json(200, {"ok": True, "message": message})

    return Handler
