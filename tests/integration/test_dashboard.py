"""The dashboard in a real browser: a server and a robot on localhost, the page in headless Chromium."""

from __future__ import annotations

import json
import shutil
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.integration.procs import ServerProcess, client, endpoint, free_port
from wfnn_server.spawn import wait_listening

pytestmark = [pytest.mark.slow, pytest.mark.multiprocess]

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")


def _browser():  # type: ignore[no-untyped-def]
    """Headless Chromium driven by Selenium, or a skip that says what is missing."""
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.skip(
            "Debian's chromium and chromium-driver are not installed (deploy/setup.sh installs them "
            "where it runs as root with apt-get)"
        )
    webdriver = pytest.importorskip(
        "selenium.webdriver", reason="selenium is not installed (pip install -e .[dev])"
    )
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    # No sandbox (tests may run as root); nothing reaches beyond loopback.
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1400,1100"):  # fmt: skip
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)


def _wait(predicate, timeout_s: float, what: str):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.25)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def test_the_dashboard_shows_live_curves_and_the_action_value_surface_in_a_browser(tmp_path):
    port, web = free_port(), free_port()
    with ServerProcess(tmp_path / "srv", port, "--dashboard", str(web)) as server:
        robot = client("--sim", "boat", "--rate-hz", "15", "--duration", "45", "--episodes", "100",
                       "--server", endpoint(port), "--out", str(tmp_path / "run"))  # fmt: skip
        browser = None
        try:
            url = f"http://127.0.0.1:{web}/"
            _wait(lambda: _stored(web) >= 15, 60, "the server to store the robot's experiences")
            browser = _browser()
            browser.get(url)
            text = lambda element_id: browser.find_element("id", element_id).text  # noqa: E731
            _wait(lambda: int(text("samples") or 0) >= 2, 30, "the page's first samples")
            first = (int(text("samples")), text("stored"), text("version"))
            # Live: the figures on the page change while the robot learns.
            _wait(lambda: int(text("samples")) >= first[0] + 4 and text("stored") != first[1]
                  and text("version") != first[2], 30, "live values to change")  # fmt: skip
            curves = browser.execute_script(
                "const d = document.getElementById('chart-learning').data;"
                "return d.map(t => t.y.filter(v => v !== null).length);"
            )
            assert len(curves) == 2 and min(curves) >= 3, curves  # reward and Q of chosen actions
            surface = browser.execute_script(
                "const d = document.getElementById('chart-surface').data;"
                "return d.map(t => [t.type || 'scatter', (t.z || t.y).length]);"
            )
            # The boat has two thrusters: a heat map over both, and its 9 wires marked.
            assert surface[0] == ["heatmap", 41] and surface[1] == ["scatter", 9], surface
            assert text("status").startswith("live")
            shot = tmp_path / "dashboard.png"
            assert browser.save_screenshot(str(shot)) and shot.stat().st_size > 20_000
            kept = Path(__file__).parents[2] / "runs" / "tests"  # kept after the test (runs/ is not tracked)
            kept.mkdir(parents=True, exist_ok=True)
            shutil.copy(shot, kept / "dashboard-e2e.png")
        finally:
            if browser is not None:
                browser.quit()
            robot.terminate()
            robot.wait(timeout=30)
        assert server.alive()


def _stored(port: int) -> int:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/view", timeout=2) as response:
            return int(json.load(response)["figures"].get("store/experiences") or 0)
    except OSError:
        return 0


def test_the_dashboard_refuses_to_change_anything(tmp_path):
    port, web = free_port(), free_port()
    with ServerProcess(tmp_path / "srv", port, "--dashboard", str(web)):
        wait_listening(web)
        request = urllib.request.Request(f"http://127.0.0.1:{web}/api/view", data=b"{}", method="POST")
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(request, timeout=5)
        assert refused.value.code == 405


def test_the_dashboard_shows_what_a_hydra_clients_cameras_saw(tmp_path):
    from tests.fakes import render_problem

    if (problem := render_problem()) is not None:
        pytest.skip(f"no off-screen rendering here: {problem}")
    port, web = free_port(), free_port()
    with ServerProcess(tmp_path / "srv", port, "--dashboard", str(web)):
        robot = client("--sim", "hydra", "--rate-hz", "15", "--duration", "40", "--camera-every", "15",
                       "--server", endpoint(port), "--out", str(tmp_path / "run"))  # fmt: skip
        browser = None
        try:
            wait_listening(web)
            ticks = _wait(lambda: _view(web).get("cameras"), 60, "a camera picture to reach the server")
            browser = _browser()
            browser.get(f"http://127.0.0.1:{web}/")
            # The picture on the page: both cameras side by side, as the client saved them.
            size = _wait(lambda: browser.execute_script(
                "const i = document.getElementById('camera');"
                "return i.complete && i.naturalWidth > 0 ? [i.naturalWidth, i.naturalHeight] : null;"
            ), 30, "the camera picture on the page")  # fmt: skip
            client_id, tick = next(iter(ticks.items()))
            saved = tmp_path / "run" / "cameras" / f"{tick:07d}.png"
            import cv2

            height, width = cv2.imread(str(saved)).shape[:2]
            assert size == [width, height] and width > height  # two cameras side by side
            later = _wait(lambda: _view(web)["cameras"][client_id] > tick and _view(web)["cameras"], 30,
                          "a newer picture")  # fmt: skip
            assert later[client_id] % 15 == 0
            browser.save_screenshot(str(tmp_path / "dashboard-hydra.png"))
        finally:
            if browser is not None:
                browser.quit()
            robot.terminate()
            robot.wait(timeout=30)


def _view(port: int) -> dict:  # type: ignore[type-arg]
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/view", timeout=2) as response:
            return dict(json.load(response))
    except OSError:
        return {}
