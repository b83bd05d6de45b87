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
import dataclasses
import heapq
import ipaddress
import itertools
import logging
import socket
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
from wfnn_server.view import CLIENT_SERIES

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


VIEW_CLIENTS = 64
"""Clients the page's table lists at most (the most recently heard; `clients_heard` counts all)."""
SAMPLED_CLIENTS = 16
"""Clients whose figures a sample keeps: the most recently heard (a sample per status, kept
`history` times, must not grow with every client id the server has ever heard)."""
RECENT_S = 5.0
"""A client whose heartbeat has not changed for this long is left out of new samples (heartbeats
come twice a second)."""
MAX_CONNECTIONS = 64
"""Connections served at once; more are closed as they arrive (each holds a thread)."""
TIMEOUT_S = 30.0
"""Socket timeout of a connection: an idle or half-sent one ends after this long, and one whose
reader stops once the kernel's buffers (megabytes) are full."""
STREAM_S = 300.0
"""An event stream ends after this long (the page reconnects at once and is sent the history
again): one whose reader never reads would otherwise hold its connection for tens of minutes
before its buffers filled."""
CPU_SHARE = 0.05
"""Of one core, the most the dashboard's connections spend over time (at a burst of CPU_BURST_S);
beyond it their requests wait. They share the interpreter's lock with the learner: viewers asking
for the whole history back to back took 97% of its thinks. A page costs about 0.1% here."""
CPU_BURST_S = 0.1
CPU_DEBT_S = 1.0
"""The most the connections owe the budget (a wait of CPU_DEBT_S / CPU_SHARE at worst)."""
HEAD_S = 10.0
"""A request's line and headers must arrive within this long: one trickled a byte at a time
(each within the socket timeout) would hold its connection's slot for good."""


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
        self._samples: collections.deque[tuple[int, bytes]] = collections.deque(maxlen=config.history)
        """(number, JSON) of each sample kept: encoded once, not in every request for the history."""
        self._cached: tuple[float, bytes] | None = None
        """(when, the view without samples as JSON bytes): made at most update_hz times a second."""
        self._grid: SurfaceGrid | None = None
        self._view_lock = threading.Lock()
        """Held while the cached view is checked and made: one thread makes it, the others reuse it."""
        self._grid_lock = threading.Lock()
        """Held while the grid is used (its compiled kernel writes scratch arrays it keeps, and the
        surface it answers may be those arrays) until the surface is encoded."""
        self._heard = _Recency()
        """When each client's heartbeat last changed (seen at each status): the server's `clients`
        keeps the order clients first arrived in. (Its states and pictures come newest last.)"""
        self._static: tuple[Any, dict[str, Any]] | None = None
        self.stopping = threading.Event()
        self.cpu_s = 0.0
        """CPU time spent by the dashboard (requests and sampling), seconds."""
        self._budget = (CPU_BURST_S, time.monotonic())
        """(CPU seconds the connections may still spend at once, when that was reckoned)."""
        self._budget_lock = threading.Lock()
        self._exempt = threading.local()
        """Per thread: CPU seconds of the shared view made since its connection was last charged."""
        self.requests = 0
        self._started = time.monotonic()  # the page trims by t: it must never run backwards
        self.page = resources.files("wfnn_server").joinpath("static", "dashboard.html").read_bytes()
        self.script = resources.files("wfnn_server").joinpath("static", "dashboard.js").read_bytes()
        self.plotly = _plotly_js()
        handler = type("Handler", (_Handler,), {"dashboard": self})
        try:
            self._http = _Server((config.host, config.port), handler)
        except OSError as exc:  # say which of the server's sockets could not be had
            raise OSError(exc.errno, f"dashboard cannot listen on {config.host} port {config.port}: "
                          f"{exc.strerror or exc}") from None  # fmt: skip
        self.port = int(self._http.server_address[1])
        # Every interface by the address bound, not by its spelling ("0" and "0.0.0.00" bind it too).
        self.every_interface = _unspecified(str(self._http.server_address[0]))
        self.hosts = _allowed_hosts(config.host, self.port, self.every_interface)
        """Host headers served (lower case): the page's own addresses, never another name (DNS rebinding)."""
        self._thread = threading.Thread(target=self._http.serve_forever, name="dashboard", daemon=True)
        view.status_listeners.append(self._sample)

    def start(self) -> Dashboard:
        """Serve in a background thread."""
        self._thread.start()
        log.info("dashboard on %s (read-only)", self.url)
        return self

    @property
    def url(self) -> str:
        """The page's address, with the port it was given."""
        return dataclasses.replace(self.config, port=self.port).url

    def stop(self) -> None:
        """Stop serving (open streams end) and close the socket."""
        self.stopping.set()
        if self._thread.ident is not None:  # shutdown waits for serve_forever, which never ran otherwise
            self._http.shutdown()
        self._http.server_close()
        if self._thread.ident is not None:  # a start that failed before serving never started it
            self._thread.join(timeout=5.0)

    # ------------------------------------------------------------------ sampling (learner thread)
    def _sample(self, status: ServerStatus) -> None:
        t0 = time.thread_time()
        m = status.metrics
        now = time.monotonic()
        view = self.view_of
        heard = self._heard.seen(view.clients, now)
        # Only what the page plots, of the most recently heard clients still heard.
        recent = [cid for cid in heard.newest(SAMPLED_CLIENTS) if now - heard.at(cid) <= RECENT_S]
        clients = {
            cid: {name: c.metrics.get(key) for name, key in CLIENT_SERIES.items()}
            for cid in recent
            if (c := view.clients.get(cid)) is not None
        }
        sample = {
            "t": round(now - self._started, 3),
            **{name: m.get(key) for name, key in SERIES.items()},
            "clients": clients,
        }
        with self._lock:
            self._seq += 1
            sample["seq"] = self._seq
            self._samples.append((self._seq, orjson.dumps(sample)))
            self.cpu_s += time.thread_time() - t0

    # ------------------------------------------------------------------ the view (HTTP threads)
    def wait_for_budget(self) -> bool:
        """Wait until the connections' CPU budget (CPU_SHARE) allows more work; False if stopping."""
        while True:
            with self._budget_lock:
                left, at = self._budget
                now = time.monotonic()
                left = min(CPU_BURST_S, left + (now - at) * CPU_SHARE)
                self._budget = (left, now)
            if left > 0.0:
                return True
            if self.stopping.wait(-left / CPU_SHARE):
                return False

    def spend(self, cpu_s: float) -> None:
        """Charge a connection's CPU time to the budget, less this thread's share of making the view."""
        cpu_s -= getattr(self._exempt, "cpu_s", 0.0)
        self._exempt.cpu_s = 0.0
        with self._budget_lock:
            left, at = self._budget
            self._budget = (max(left - cpu_s, -CPU_DEBT_S), at)

    def host_allowed(self, hosts: list[str]) -> bool:
        """Whether a request's Host headers (all of them) name this dashboard.

        One header, of its own addresses, or, where it serves every interface, any IP address
        with its port (on port 80 also without, as browsers send it).
        """
        if len(hosts) != 1:
            return False
        host = hosts[0].strip().lower()
        if host in self.hosts:
            return True
        if not (self.every_interface and _ip_literal(host)):
            return False
        if host.endswith("]") or ":" not in host:  # no port: HTTP's default
            return self.port == 80
        return host.rpartition(":")[2] == str(self.port)

    def view(self, since: int = 0) -> dict[str, Any]:
        """Everything the page shows, with only the samples newer than `since`."""
        view: dict[str, Any] = orjson.loads(self.view_json(since))
        return view

    def view_json(self, since: int = 0) -> bytes:
        """`view` as the JSON bytes the page gets."""
        return self._view_json(since)[0]

    def _view_json(self, since: int) -> tuple[bytes, int]:
        """(`view_json`, the newest sample's number in it, or `since` if none)."""
        with self._view_lock:
            now = time.monotonic()
            cached = self._cached
            if cached is None or now - cached[0] >= 1.0 / self.config.update_hz:
                t0 = time.thread_time()
                cached = (now, orjson.dumps(self._current()))
                self._cached = cached
                # Not the viewers' to pay: made at most update_hz times a second however many
                # ask (the first surface compiles its kernel, seconds that froze the page after).
                self._exempt.cpu_s = getattr(self._exempt, "cpu_s", 0.0) + time.thread_time() - t0
        with self._lock:
            # The newest first, back to `since`: work in proportion to what is new, not to the
            # history kept (a page that keeps up gets one or two samples an update).
            samples = list(itertools.takewhile(lambda s: s[0] > since, reversed(self._samples)))[::-1]
            extra = {"requests": self.requests,
                     "cpu": {"dashboard_s": self.cpu_s, "process_s": time.process_time()}}  # fmt: skip
        newest = samples[-1][0] if samples else since
        head = b'{"samples":[' + b",".join(s for _, s in samples) + b"]," + orjson.dumps(extra)[1:-1]
        return head + b"," + cached[1][1:], newest

    def _shown_clients(self, clients: dict[str, Any]) -> list[str]:
        """The clients the page's table lists: all, or the VIEW_CLIENTS most recently heard.

        A server keeps up to MAX_HEARD (4,096, forged ids included without a key): all of them,
        in every update to every viewer, came to 600 KB four times a second.
        """
        if len(clients) <= VIEW_CLIENTS:
            return list(clients)
        return self._heard.newest(VIEW_CLIENTS)

    def _current(self) -> dict[str, Any]:
        srv = self.view_of
        status = srv.last_status
        cameras = srv.camera_views
        cfg = srv.learner_config
        if self._static is None or self._static[0] is not cfg:  # what changes only with the config
            self._static = (cfg, {
                "server": srv.server, "incarnation": srv.incarnation, "controller": srv.controller,
                "learner": cfg.short_repr() if cfg is not None else None, "update_hz": self.config.update_hz,
                "history": self.config.history,
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
                for cid in self._shown_clients(srv.clients)
                if (c := srv.clients.get(cid)) is not None
            },
            "clients_heard": len(srv.clients),
            "surface": None,
            "cameras": {cid: v.tick for cid, v in cameras.items()},
            "camera": next(reversed(cameras), None),  # the server keeps the newest picture last
        }
        params = srv.published
        # The newest state a client sent (the server keeps it last; a non-finite one is never
        # learned from nor drawn).
        states = {cid: s for cid, s in srv.latest_state.items() if bool(np.isfinite(s).all())}
        client = next(reversed(states), None)
        if cfg is not None and params is not None and client is not None:
            state = states[client]
            with self._grid_lock:  # the grid's compiled kernel writes scratch arrays it keeps
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


class _Recency:
    """When each client's entry of the server's `clients` last changed, as the sampler saw.

    The server replaces the values whole, never changing one in place, and that dict keeps the
    order clients first arrived in, not the order they were last heard in.
    """

    def __init__(self) -> None:
        self._seen: dict[str, tuple[object, float, int]] = {}
        """Per client: (the value seen, when it was first seen, a count that orders ties)."""
        self._count = 0

    def seen(self, current: dict[str, Any], now: float) -> _Recency:
        """Note the values of `current` (clients gone from it are forgotten)."""
        old, new = self._seen, {}
        for cid, value in current.items():
            was = old.get(cid)
            if was is None or was[0] is not value:
                self._count += 1
                was = (value, now, self._count)
            new[cid] = was
        self._seen = new  # replaced whole: other threads read it
        return self

    def at(self, cid: str) -> float:
        """When `cid`'s value last changed (monotonic seconds)."""
        return self._seen[cid][1]

    def newest(self, n: int) -> list[str]:
        """The `n` clients whose value changed most recently, the newest first."""
        return [cid for cid, _ in heapq.nlargest(n, self._seen.items(), key=lambda item: item[1][1:])]


WILDCARDS = ("0.0.0.0", "::")
"""Hosts that bind every interface (an empty one is refused by `DashboardConfig`)."""


def _host_name(host: str) -> str:
    """A host as a Host header names it: IPv6 addresses in brackets, lower case."""
    return f"[{host}]".lower() if ":" in host else host.lower()


def _unspecified(address: str) -> bool:
    """Whether a bound address is every interface's (0.0.0.0 or ::)."""
    try:
        return ipaddress.ip_address(address.split("%", 1)[0]).is_unspecified
    except ValueError:
        return False


def _allowed_hosts(host: str, port: int, every_interface: bool = False) -> frozenset[str]:
    """The Host headers the dashboard serves: its own address and the loopback names.

    With its port, and without where the port is HTTP's default, as browsers send it.
    """
    names = {"127.0.0.1", "localhost", "[::1]", _host_name(host)}
    if every_interface or host in WILDCARDS:  # serving every interface: the machine's own names too
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
    hosts = {f"{name}:{port}" for name in names}
    if port == 80:
        hosts |= names
    return frozenset(hosts)


def _ip_literal(host: str) -> bool:
    name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
    try:
        ipaddress.ip_address(name[1:-1] if name.startswith("[") else name)
    except ValueError:
        return False
    return True


class _Server(ThreadingHTTPServer):
    """The standard library's threading HTTP server, serving at most MAX_CONNECTIONS at once.

    A connection's failure (a page gone mid-response) is logged at debug level, not printed.
    """

    daemon_threads = True
    # The listen backlog: the standard library's 5 dropped connections made in a burst (a page
    # opens about 3 at once) before the accepting thread took them.
    request_queue_size = MAX_CONNECTIONS

    def __init__(self, address: tuple[str, int], handler: type[BaseHTTPRequestHandler]) -> None:
        if ":" in address[0]:
            self.address_family = socket.AF_INET6
        super().__init__(address, handler)
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self.slots.acquire(blocking=False):
            log.debug("dashboard: %d connections open, one from %s closed", MAX_CONNECTIONS, client_address)
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()

    def handle_error(self, request: Any, client_address: Any) -> None:
        log.debug("dashboard: connection from %s failed", client_address, exc_info=True)


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
    timeout = TIMEOUT_S  # an idle, half-sent or unread connection ends rather than holding its thread
    _head_timer: threading.Timer | None = None
    _charged = 0.0
    """This thread's CPU time when last charged to the dashboard's budget."""

    def handle_one_request(self) -> None:
        """One request, its head (line and headers) due within HEAD_S or the connection is cut.

        Served once the dashboard's CPU budget allows (`Dashboard.wait_for_budget`), and charged to it.
        """
        if not self.dashboard.wait_for_budget():
            self.close_connection = True
            return
        self._charged = time.thread_time()
        timer = threading.Timer(HEAD_S, self._cut)
        timer.daemon = True
        self._head_timer = timer
        timer.start()
        try:
            super().handle_one_request()
        finally:
            timer.cancel()
            # The timer holds this handler (its `_cut`): a cycle that kept the connection's socket
            # open until the cyclic collector ran.
            self._head_timer = None
            self._charge()

    def finish(self) -> None:
        """Close the connection's files, the reading one too where writing fails (a reset peer).

        The standard finish closed the writing file first; a reset made that raise, and the
        reading file kept the socket open after the connection ended.
        """
        try:
            super().finish()
        except OSError:
            pass  # the peer went: nothing is left to send it
        finally:
            self.rfile.close()

    def _charge(self) -> None:
        """Charge this thread's CPU time since the last charge to the dashboard's budget."""
        now = time.thread_time()
        self.dashboard.spend(now - self._charged)
        self._charged = now

    def _cut(self) -> None:
        try:
            self.connection.shutdown(socket.SHUT_RDWR)  # the blocked read returns: the handler ends
        except OSError:
            pass

    def parse_request(self) -> bool:
        """The standard parsing, then the Host header checked.

        A page of another name that resolves to this address (DNS rebinding) gets nothing.
        """
        parsed = super().parse_request()
        if self._head_timer is not None:  # the head has arrived: a stream may last
            self._head_timer.cancel()
        if not parsed:
            return False
        if self.dashboard.host_allowed(self.headers.get_all("Host") or []):
            return True
        self._send(b"", "text/plain", HTTPStatus.MISDIRECTED_REQUEST, close=True)
        return False

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
        self.close_connection = True
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.flush()  # the messages go straight to the socket, one send each
        except OSError:  # the page went away (or stopped reading)
            return
        period = 1.0 / d.config.update_hz
        next_at = time.monotonic()
        ends = next_at + STREAM_S
        while not d.stopping.is_set() and time.monotonic() < ends:
            self._charge()
            if not d.wait_for_budget():
                break
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

    def _refuse(self) -> None:
        # Closed after the reply: a body it sent, unread, would otherwise be read as the next request.
        self._send(b"read-only", "text/plain", HTTPStatus.METHOD_NOT_ALLOWED, allow="GET", close=True)

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse  # noqa: N815 (the standard library's names)

    def __getattr__(self, name: str) -> Any:
        """Any other method (TRACE, CONNECT, WebDAV's, a misspelt one) is refused as read-only too."""
        if name.startswith("do_"):
            return self._refuse
        raise AttributeError(name)

    def do_HEAD(self) -> None:
        """405 as for the other methods, with no body: a reply to HEAD never carries one."""
        try:
            self.send_response(HTTPStatus.METHOD_NOT_ALLOWED)
            self.send_header("Allow", "GET")
            self.send_header("Content-Length", "0")
            self.end_headers()
            self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, TimeoutError):  # the page went away
            self.close_connection = True

    def _send(
        self,
        body: bytes,
        kind: str,
        status: HTTPStatus = HTTPStatus.OK,
        cache: bool = False,
        allow: str = "",
        close: bool = False,
    ) -> None:
        try:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "max-age=3600" if cache else "no-store")
            if allow:
                self.send_header("Allow", allow)
            if close:
                self.send_header("Connection", "close")
            self.end_headers()
            self.wfile.write(body)
            self.wfile.flush()
        except (BrokenPipeError, ConnectionResetError, TimeoutError) as exc:  # the page went away
            self.close_connection = True
            log.debug("dashboard: %s: %s", self.path, exc)

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("dashboard: " + format, *args)
