"""The dashboard's JSON view and HTTP surface (in-process server on the in-memory bus)."""

import base64
import json
import socket
import urllib.error
import urllib.request

import numpy as np
import pytest

from tests.fakes import Hub, small_config, wait_for
from tests.unit.wfnn_server.test_server import KEYS, Listener, batch, make_server, send
from wfnn_common.learner import WFNN
from wfnn_io.protocol import ClientStatus, Codec
from wfnn_server.config import DashboardConfig


def _get(port, path):
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as response:
        return response.status, response.headers.get("Content-Type"), response.read()


def _heartbeat(hub, cfg, client="c1", jitter=0.2):
    status = ClientStatus(
        client=client, spec_hash=cfg.spec_hash(), learner_config=cfg.to_json(), following="s1",
        weights_version=3, produced_through=5, acked={},
        metrics={"client/tick_jitter_ms_p99": jitter, "client/overruns": 1.0, "client/reward_mean": -0.5},
    )  # fmt: skip
    hub.bus().put(KEYS.client_status(client), Codec(client).encode(status), None)


def test_the_view_has_the_servers_figures_clients_and_the_action_value_surface(tmp_path):
    hub, cfg = Hub(), small_config(thinks_per_action=3)
    listener = Listener(hub)
    with make_server(tmp_path, hub, cfg, dashboard=DashboardConfig(port=0, update_hz=30)) as server:
        port = server.dashboard.port
        status, kind, page = _get(port, "/")
        assert status == 200 and kind.startswith("text/html") and b"/static/plotly.min.js" in page
        assert b"Plotly" in _get(port, "/static/plotly.min.js")[2][:5000]
        b = batch(cfg, 0, 6)
        send(hub, b)
        _heartbeat(hub, cfg)
        assert listener.wait(lambda: listener.acked() == 5)
        assert wait_for(lambda: "c1" in json.loads(_get(port, "/api/view")[2])["clients"])

        def view(since=0):
            return json.loads(_get(port, f"/api/view?since={since}")[2])

        # A status published before the batch was stored may still be the newest for a moment.
        assert wait_for(lambda: view()["surface"] is not None and len(view()["samples"]) >= 2
                        and view()["figures"].get("store/experiences") == 6)  # fmt: skip
        v = view()
        assert v["server"] == "s1" and v["figures"]["store/experiences"] == 6
        # The mean reward of the status window the batch arrived in (later windows have none).
        rewards = [s["reward"] for s in v["samples"] if s["reward"] is not None]
        assert rewards == [pytest.approx(float(b.reward.mean()), abs=1e-9)]
        assert (
            v["clients"]["c1"]["following"] == "s1" and v["clients"]["c1"]["metrics"]["client/overruns"] == 1
        )
        last = v["samples"][-1]
        assert last["clients"]["c1"]["jitter_p99_ms"] == pytest.approx(0.2)
        # Only samples newer than `since` come back.
        newer = view(last["seq"])["samples"]
        assert all(s["seq"] > last["seq"] for s in newer)
        # The surface: Q over both actions at the newest state, as the learner's own wire fitting says.
        surface = v["surface"]
        assert surface["client"] == "c1" and surface["dims"] == [0, 1]

        def f32(key):
            return np.frombuffer(base64.b64decode(surface[f"{key}_f32"]), dtype="<f4")

        q = f32("q").reshape(surface["shape"])
        assert q.shape == (41, 41) and len(f32("wire_value")) == surface["n_wires"] == cfg.n_wires
        assert f32("wire_action").shape == (cfg.n_wires * 2,)
        axes = [np.linspace(*a) for a in surface["axes"]]
        state = f32("state").astype(np.float64)
        np.testing.assert_allclose(state, b.next_state[-1], atol=1e-6)
        state = b.next_state[-1]
        j, i = 7, 30
        # Once the thinks owed are done the weights hold still, and the surface drawn since is theirs
        # (one drawn earlier may be of weights the server has thought past: it failed under load).
        assert wait_for(server.replayed)
        learner = WFNN(cfg, params=server.view.published)
        expected = float(learner.q_value(state, [axes[0][i], axes[1][j]]))

        def drawn_now():
            surface = view()["surface"]
            q = np.frombuffer(base64.b64decode(surface["q_f32"]), dtype="<f4").reshape(surface["shape"])
            return abs(float(q[j, i]) - expected) < 1e-5

        assert wait_for(drawn_now)
        assert v["cpu"]["dashboard_s"] > 0 and v["requests"] >= 3


def test_bad_requests_are_refused_and_nothing_can_be_changed(tmp_path):
    hub, cfg = Hub(), small_config()
    with make_server(tmp_path, hub, cfg, dashboard=DashboardConfig(port=0)) as server:
        port = server.dashboard.port
        for path, code in (("/nothing", 404), ("/api/view?since=x", 400), ("/api/stream?since=x", 400)):
            with pytest.raises(urllib.error.HTTPError) as refused:
                _get(port, path)
            assert refused.value.code == code
        for method in ("POST", "PUT", "DELETE", "OPTIONS"):
            request = urllib.request.Request(f"http://127.0.0.1:{port}/api/view", data=b"{}", method=method)
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(request, timeout=5)
            assert refused.value.code == 405 and refused.value.headers["Allow"] == "GET"
        with pytest.raises(urllib.error.HTTPError) as refused:  # HEAD too, and its reply has no body
            head = urllib.request.Request(f"http://127.0.0.1:{port}/", method="HEAD")
            urllib.request.urlopen(head, timeout=5)
        assert refused.value.code == 405 and refused.value.headers["Content-Length"] == "0"
    with pytest.raises(urllib.error.URLError):  # stopped with the server
        _get(port, "/")


def test_the_dashboard_is_off_by_default_and_checks_its_config(tmp_path):
    with make_server(tmp_path, Hub(), small_config()) as server:
        assert server.dashboard is None
    for bad in ({"port": 70000}, {"port": 0, "update_hz": 0.0}, {"port": 0, "history": 2}):
        with pytest.raises(ValueError):
            DashboardConfig(**bad)


def test_a_clients_camera_pictures_are_shown_as_they_arrive(tmp_path):
    import cv2

    from wfnn_io.protocol import CameraView

    hub, cfg = Hub(), small_config()
    picture = np.zeros((12, 20, 3), dtype=np.uint8)
    picture[:, :10] = 255
    png = cv2.imencode(".png", picture)[1].ravel()
    with make_server(tmp_path, hub, cfg, dashboard=DashboardConfig(port=0, update_hz=30)) as server:
        port = server.dashboard.port
        with pytest.raises(urllib.error.HTTPError) as missing:
            _get(port, "/api/camera/c1.png")
        assert missing.value.code == 404
        hub.bus().put(
            KEYS.camera_view("c1"), Codec("c1").encode(CameraView(client="c1", tick=75, png=png)), None
        )
        # A picture claiming to be another client's is refused.
        hub.bus().put(
            KEYS.camera_view("c2"), Codec("c1").encode(CameraView(client="c2", tick=1, png=png)), None
        )
        assert wait_for(lambda: json.loads(_get(port, "/api/view")[2])["cameras"] == {"c1": 75})
        assert wait_for(lambda: server.rejected["sender"] == 1)
        status, kind, body = _get(port, "/api/camera/c1.png")
        assert status == 200 and kind == "image/png"
        np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR), picture)


def test_a_dashboard_port_in_use_stops_the_start_before_anything_is_heard(tmp_path):
    hub = Hub()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        server = make_server(tmp_path, hub, small_config(), dashboard=DashboardConfig(port=port))
        with pytest.raises(OSError, match=f"dashboard cannot listen on 127.0.0.1 port {port}"):
            server.start()
    assert not hub.subscribers and not hub.queryables and not hub.tokens  # no experience taken, none acked
    server.stop()  # stopping a server whose start failed returns (the dashboard never served)


def test_an_ipv6_dashboard_host_may_come_in_brackets():
    assert DashboardConfig(port=8080, host="[::1]").host == "::1"
    assert DashboardConfig(port=8080, host="::1").url == "http://[::1]:8080/"
    assert DashboardConfig(port=8080, host="[::1]").loopback


def test_the_samples_time_axis_never_runs_backwards_when_the_wall_clock_is_set_back(tmp_path, monkeypatch):
    """The page trims each curve by its samples' t, assuming t only grows (as a corrected clock's
    wall time need not): a step back left the clients' curves growing without bound."""
    import time

    hub, cfg = Hub(), small_config()
    with make_server(tmp_path, hub, cfg, dashboard=DashboardConfig(port=0, update_hz=30)) as server:
        port = server.dashboard.port

        def samples():
            return json.loads(_get(port, "/api/view")[2])["samples"]

        assert wait_for(lambda: len(samples()) >= 3)
        before = len(samples())
        wall = time.time
        monkeypatch.setattr(time, "time", lambda: wall() - 3600.0)  # the clock set back an hour
        assert wait_for(lambda: len(samples()) >= before + 3)
        t = [s["t"] for s in samples()]
        assert t == sorted(t) and t[0] >= 0.0


def test_a_connection_its_peer_resets_is_closed_as_it_ends():
    """A reset peer failed the writing file's close, so the reading one held the socket open; and a
    cycle through the head timer held the handler: sockets stayed open until the cyclic collector
    ran (4,800 short connections, half of them reset, left one more open every few hundred)."""
    import gc
    import os
    import struct

    from wfnn_server.dashboard import Dashboard
    from wfnn_server.view import ViewModel

    def sockets() -> int:
        n = 0
        for fd in os.listdir("/proc/self/fd"):
            try:
                n += os.readlink(f"/proc/self/fd/{fd}").startswith("socket:")
            except OSError:
                pass  # closed meanwhile (the listing's own, or another thread's)
        return n

    view = ViewModel(server="s", incarnation=1, controller="c")
    dashboard = Dashboard(DashboardConfig(port=0), view).start()
    gc.disable()  # the leak hid behind the collector
    try:
        before = sockets()
        for _ in range(40):
            peer = socket.create_connection(("127.0.0.1", dashboard.port))
            peer.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{dashboard.port}\r\n\r\n".encode())
            peer.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # close: a reset
            peer.close()
        assert wait_for(lambda: sockets() <= before + 2, timeout=10.0), sockets() - before
    finally:
        gc.enable()
        dashboard.stop()
