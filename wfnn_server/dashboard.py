"""A live, read-only web view of a think server (`wfnn-server --dashboard PORT`).

The page (`static/dashboard.html`, drawn with Plotly.js, served from the installed `plotly`
package so it works with no network) opens one server-sent-events stream (`/api/stream`) and
gets the view `update_hz` times a second as JSON: the samples of the server's figures it has not
seen yet (reward and Q of chosen actions, thinks/s, experiences stored, divergence resets),
frames rejected by reason, each client's latest heartbeat figures (tick jitter, overruns, the
server it follows), the action-value surface of the newest state a client sent with the wires
marked, and which camera pictures have arrived (`/api/camera/<client>.png`). `/api/view?since=N`
answers the same view once.

Read-only by construction: only GET is served, and the view only reads what the server's
threads publish (whole objects replaced, never changed in place). The HTTP server is the
standard library's, one thread per connection (keep-alive), bound to 127.0.0.1 unless told
otherwise. The CPU time the dashboard's threads spend is counted (`cpu_s`) and reported in the
view, so its cost next to the server's own is measured where it runs.
"""

from __future__ import annotations

import base64
import collections
import itertools
import logging
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, urlparse

import numpy as np
import orjson

from wfnn_common.surface import SurfaceGrid
from wfnn_io.protocol import ServerStatus
from wfnn_server.config import DashboardConfig

if TYPE_CHECKING:
    from wfnn_server.view import ViewModel

log = logging.getLogger(__name__)

SERIES = {
    "reward": "learn/reward_mean",
    "q_chosen": "learn/q_chosen_mean",
    "thinks_per_s": "think/thinks_per_s",
    "stored": "store/experiences",
    "resets": "learn/divergence_resets",
}
"""Plotted server figures: name on the page -> ServerStatus metric (JSON by orjson: NaN and a
missing figure both travel as null, a gap in a curve)."""

FIGURES = ("think/thinks_per_s", "store/experiences", "learn/divergence_resets", "learn/reward_mean",
           "learn/q_chosen_mean")  # fmt: skip
"""Server figures shown as numbers (the view sends only what the page shows)."""

CLIENT_SERIES = {
    "reward": "client/reward_mean",
    "q": "client/q_mean",
    "jitter_p99_ms": "client/tick_jitter_ms_p99",
    "overruns": "client/overruns",
}
"""Plotted client figures: name on the page -> ClientStatus metric."""


def _f32(values: np.ndarray) -> str:
    """An array as base64 of little-endian float32, which the page reads as a Float32Array.

    A 41 x 41 surface encodes in microseconds rather than the JSON of 1,681 floats.
    """
    return base64.b64encode(np.ascontiguousarray(values, dtype="<f4").tobytes()).decode()


class Dashboard:
    """Serves the page and its JSON view of one think server (its `ViewModel`) from background threads."""

    def __init__(self, config: DashboardConfig, view: ViewModel) -> None:
        self.config = config
        self.view_of = view
        """What the server publishes for views (never the server itself)."""
        self._lock = threading.Lock()
        self._seq = 0
        self._samples: collections.deque[dict[str, Any]] = collections.deque(maxlen=config.history)
        self._cached: tuple[float, bytes] | None = None
        """(when, the view without samples as JSON bytes): made at most update_hz times a second."""
        self._grid: SurfaceGrid | None = None
        self._static: tuple[Any, dict[str, Any]] | None = None
        self.stopping = threading.Event()
        self.cpu_s = 0.0
        """CPU time spent by the dashboard (requests and sampling), seconds."""
        self.requests = 0
        self._started = time.time()
        self.page = resources.files("wfnn_server").joinpath("static", "dashboard.html").read_bytes()
        self.script = resources.files("wfnn_server").joinpath("static", "dashboard.js").read_bytes()
        self.plotly = _plotly_js()
        handler = type("Handler", (_Handler,), {"dashboard": self})
        self._http = ThreadingHTTPServer((config.host, config.port), handler)
        self._http.daemon_threads = True
        self.port = int(self._http.server_address[1])
        self._thread = threading.Thread(target=self._http.serve_forever, name="dashboard", daemon=True)
        view.status_listeners.append(self._sample)

    def start(self) -> Dashboard:
        """Serve in a background thread."""
        self._thread.start()
        log.info("dashboard on http://%s:%d/ (read-only)", self.config.host, self.port)
        return self

    def stop(self) -> None:
        """Stop serving (open streams end) and close the socket."""
        self.stopping.set()
        self._http.shutdown()
        self._http.server_close()
        self._thread.join(timeout=5.0)

    # ------------------------------------------------------------------ sampling (learner thread)
    def _sample(self, status: ServerStatus) -> None:
        t0 = time.thread_time()
        m = status.metrics
        clients = {
            cid: {
                **{name: c.metrics.get(key) for name, key in CLIENT_SERIES.items()},
                "following": c.following,
                "weights_version": c.weights_version,
            }
            for cid, c in self.view_of.clients.items()
        }
        sample = {
            "t": round(time.time() - self._started, 3),
            **{name: m.get(key) for name, key in SERIES.items()},
            "clients": clients,
        }
        with self._lock:
            self._seq += 1
            sample["seq"] = self._seq
            self._samples.append(sample)
            self.cpu_s += time.thread_time() - t0

    # ------------------------------------------------------------------ the view (HTTP threads)
    def view(self, since: int = 0) -> dict[str, Any]:
        """Everything the page shows, with only the samples newer than `since`."""
        view: dict[str, Any] = orjson.loads(self.view_json(since))
        return view

    def view_json(self, since: int = 0) -> bytes:
        """`view` as the JSON bytes the page gets."""
        return self._view_json(since)[0]

    def _view_json(self, since: int) -> tuple[bytes, int]:
        """(`view_json`, the newest sample's number in it, or `since` if none)."""
        now = time.monotonic()
        cached = self._cached
        if cached is None or now - cached[0] >= 1.0 / self.config.update_hz:
            cached = (now, orjson.dumps(self._current()))
            self._cached = cached
        with self._lock:
            # The newest first, back to `since`: work in proportion to what is new, not to the
            # history kept (a page that keeps up gets one or two samples an update).
            samples = list(itertools.takewhile(lambda s: s["seq"] > since, reversed(self._samples)))[::-1]
            extra = {"samples": samples, "requests": self.requests,
                     "cpu": {"dashboard_s": self.cpu_s, "process_s": time.process_time()}}  # fmt: skip
        newest = samples[-1]["seq"] if samples else since
        return orjson.dumps(extra)[:-1] + b"," + cached[1][1:], newest

    def _current(self) -> dict[str, Any]:
        srv = self.view_of
        status = srv.last_status
        cfg = srv.learner_config
        if self._static is None or self._static[0] is not cfg:  # what changes only with the config
            self._static = (cfg, {
                "server": srv.server, "incarnation": srv.incarnation, "controller": srv.controller,
                "learner": cfg.short_repr() if cfg is not None else None, "update_hz": self.config.update_hz,
            })  # fmt: skip
        view: dict[str, Any] = {
            **self._static[1],
            "weights_version": srv.weights_version,
            "rejected": dict(status.rejected) if status is not None else {},
            "figures": {k: status.metrics.get(k) for k in FIGURES} if status is not None else {},
            "clients": {
                cid: {
                    "following": c.following,
                    "weights_version": c.weights_version,
                    "metrics": {k: c.metrics.get(k) for k in CLIENT_SERIES.values()},
                }
                for cid, c in srv.clients.items()
            },
            "surface": None,
            "cameras": {cid: v.tick for cid, v in srv.camera_views.items()},
        }
        params, states = srv.published, srv.latest_state
        if cfg is not None and params is not None and states:
            client = sorted(states)[0]
            state = states[client]
            if self._grid is None or self._grid.config is not cfg:
                dims = (0, 1) if cfg.action_dim >= 2 else (0,)
                self._grid = SurfaceGrid(cfg, dims, self.config.surface_points)
            surface = self._grid(params, state)
            # Arrays as float32 base64: formatting floats was most of the view's JSON time.
            view["surface"] = {
                "client": client,
                "dims": list(surface.dims),
                "axes": [[float(a[0]), float(a[-1]), len(a)] for a in surface.axes],
                "shape": list(surface.q.shape),
                "best": surface.best,
                "n_wires": len(surface.wire_value),
                **{f"{k}_f32": _f32(v) for k, v in (("state", state), ("q", surface.q),
                   ("wire_action", surface.wire_action), ("wire_value", surface.wire_value))},
            }  # fmt: skip
        return view


def _plotly_js() -> bytes:
    """Plotly.js as the installed `plotly` package ships it (no network needed)."""
    import plotly

    return (Path(plotly.__file__).parent / "package_data" / "plotly.min.js").read_bytes()


class _Handler(BaseHTTPRequestHandler):
    """GET only: the page, its script, Plotly.js and the JSON view."""

    dashboard: Dashboard
    protocol_version = "HTTP/1.1"  # keep-alive: a polling page reuses one connection
    # Headers and body leave in one segment: with Nagle's algorithm and delayed ACKs a small
    # body written after the headers waits ~40 ms on a keep-alive connection.
    disable_nagle_algorithm = True
    wbufsize = 1 << 16
    server_version = "wfnn-dashboard"

    def do_GET(self) -> None:
        t0 = time.thread_time()
        d = self.dashboard
        url = urlparse(self.path)
        since: int | None = 0
        if url.path in ("/api/view", "/api/stream"):
            try:
                since = int(parse_qs(url.query).get("since", ["0"])[0])
            except ValueError:
                since = None
        if url.path == "/api/stream" and since is not None:  # counts its own CPU time, message by message
            self._stream(since, t0)
            return
        try:
            if url.path in ("/", "/index.html"):
                self._send(d.page, "text/html; charset=utf-8")
            elif url.path == "/static/dashboard.js":
                self._send(d.script, "text/javascript; charset=utf-8")
            elif url.path == "/static/plotly.min.js":
                self._send(d.plotly, "text/javascript; charset=utf-8", cache=True)
            elif url.path.startswith("/api/camera/") and url.path.endswith(".png"):
                view = d.view_of.camera_views.get(url.path[len("/api/camera/") : -len(".png")])
                if view is None:
                    self._send(b"no pictures from that client", "text/plain", HTTPStatus.NOT_FOUND)
                else:
                    self._send(view.png.tobytes(), "image/png")
            elif since is None:
                self._send(
                    b'{"error": "since must be an integer"}', "application/json", HTTPStatus.BAD_REQUEST
                )
            elif url.path == "/api/view":
                self._send(d.view_json(since), "application/json")
            else:
                self._send(b"not found", "text/plain", HTTPStatus.NOT_FOUND)
        finally:
            with d._lock:
                d.requests += 1
                d.cpu_s += time.thread_time() - t0

    def _stream(self, since: int, t0: float) -> None:
        """Server-sent events: the view, update_hz times a second, until the page goes away.

        One request per page instead of one per update: the per-request header parsing is
        paid once.
        """
        d = self.dashboard
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.flush()  # the messages go straight to the socket, one send each
        period = 1.0 / d.config.update_hz
        next_at = time.monotonic()
        while not d.stopping.is_set():
            body, since = d._view_json(since)
            try:
                self.connection.sendall(b"data: " + body + b"\n\n")
            except OSError:  # the page went away
                break
            finally:
                t1 = time.thread_time()
                with d._lock:
                    d.requests += 1
                    d.cpu_s += t1 - t0
            next_at += period
            if d.stopping.wait(max(0.0, next_at - time.monotonic())):
                break
            t0 = time.thread_time()
        self.close_connection = True

    def _refuse(self) -> None:
        self._send(b"read-only", "text/plain", HTTPStatus.METHOD_NOT_ALLOWED, allow="GET")

    do_POST = do_PUT = do_DELETE = do_PATCH = _refuse  # noqa: N815 (the standard library's names)

    def _send(
        self, body: bytes, kind: str, status: HTTPStatus = HTTPStatus.OK, cache: bool = False, allow: str = ""
    ) -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
        if allow:
            self.send_header("Allow", allow)
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("dashboard: " + format, *args)
