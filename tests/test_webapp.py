"""The driver app in a browser (issue 20): ``hil run --driver web`` serves the page on
127.0.0.1; headless Chromium (Debian's, driven by Selenium through Debian's chromedriver: no
browser download) shows the recommendation, a click accepts it, and the ECU's active mode
changes on the bus. The page's screenshot is the test's output
(``out/test-artifacts/driver_page*.png``). The server's own checks (token, host, bad
requests) without a browser."""

import json
import shutil
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from firmware.params import MODE_NAMES
from hil.nodes import ID
from hil.transport.buslog import read_log
from hil.transport.codec import Codec

ROOT = Path(__file__).resolve().parents[1]
ARTIFACTS = ROOT / "out" / "test-artifacts"
pytestmark = pytest.mark.hil


def _browser():
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if not (chromium and driver):
        pytest.skip("Debian's chromium and chromium-driver are not installed (as root: "
                    "apt-get install chromium chromium-driver; .ci/run installs them)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1100,800"):
        opts.add_argument(arg)
    return webdriver.Chrome(service=Service(executable_path=driver), options=opts)


def test_the_driver_accepts_in_chromium_and_the_ecu_follows_on_the_bus(tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    browser = _browser()
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "hil", "run", "--driver", "web", "--route", "city",
         "--duration", "40", "--out", str(out), "--json", "--pace", "lockstep"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # (lockstep: deterministic, and the click lands within a simulated second of the page
    # showing the recommendation; a person drives at the car's pace, the default with
    # --driver web: realtime, whose deadlines are a benchmark matter on a busy test host)
    err: list[str] = []
    url = _page_url(proc, err)
    try:
        browser.get(url)
        wait = WebDriverWait(browser, 60, poll_frequency=0.1)
        # the page shows a recommendation, with the grade and why, that is not yet active
        wait.until(lambda b: b.find_element(By.ID, "recommended").text.lower()
                   in MODE_NAMES[1:]
                   and b.find_element(By.ID, "active").text.lower() == "passive")
        rec = browser.find_element(By.ID, "recommended").text.lower()
        why = browser.find_element(By.ID, "why").text
        assert "grade" in why and rec in why, why
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        browser.save_screenshot(str(ARTIFACTS / "driver_page_before.png"))
        browser.find_element(By.ID, "accept").click()
        wait.until(lambda b: b.find_element(By.ID, "active").text.lower() == rec)
        browser.save_screenshot(str(ARTIFACTS / "driver_page.png"))
    finally:
        browser.quit()
        stdout, rest = proc.communicate(timeout=300)
    rep = json.loads(stdout)
    assert proc.returncode == 0, ("".join(err) + rest[-2000:],
                                  [c for c in rep.get("checks", []) if not c["ok"]])
    assert rep["bench"]["pace"] == "lockstep" and rep["driver"]["policy"] == "web"
    # on the bus: the app's accept, then the ECU's status with the recommended mode active
    codec = Codec()
    frames = read_log(out / "bus.log")
    accept = next(i for i, (_, fid, data) in enumerate(frames) if fid == ID["DRIVER_REQUEST"]
                  and codec.decode(fid, data).signals["REQ_KIND"] == 1)
    active = [codec.decode(fid, data).signals["ACTIVE_MODE"]
              for _, fid, data in frames if fid == ID["ECU_STATUS"]]
    assert set(active[:10]) == {0}                               # passive until the click
    after = [codec.decode(fid, data).signals["ACTIVE_MODE"]
             for _, fid, data in frames[accept:] if fid == ID["ECU_STATUS"]]
    assert MODE_NAMES.index(rec) in after
    app = json.loads((out / "app.json").read_text())
    assert app["requests"].get("accept") == 1


def _page_url(proc, err: list[str]) -> str:
    """The URL ``hil run`` prints for the page (stderr is drained on in a thread)."""
    found = threading.Event()
    url = []

    def drain():
        for line in proc.stderr:
            err.append(line)
            if line.startswith("driver page: ") and not url:
                url.append(line.split()[2])
                found.set()
        found.set()
    threading.Thread(target=drain, daemon=True).start()
    assert found.wait(300) and url, "".join(err)[-3000:]
    return url[0]


def test_the_page_takes_requests_only_with_its_token_and_host():
    """Without a browser: the server binds 127.0.0.1, refuses a request without the page's
    token (403), one addressed to another host (403), a bad one (400), and queues a good one
    for the app node."""
    from hil.nodes import AppNode
    from hil.apps.webapp import WebApp

    node = AppNode(Codec(), "web")
    web = WebApp(node)
    url = web.start()
    try:
        assert url.startswith("http://127.0.0.1:")
        page = urllib.request.urlopen(url, timeout=10).read().decode()
        assert web.token in page and 'id="accept"' in page
        state = json.load(urllib.request.urlopen(url + "state", timeout=10))
        assert state["modes"] == list(MODE_NAMES) and state["recommended"] is None

        def post(body, token=web.token, host=None):
            req = urllib.request.Request(url + "request", data=json.dumps(body).encode(),
                                         method="POST", headers={"X-Driver-Token": token})
            if host:
                req.add_header("Host", host)
            try:
                return urllib.request.urlopen(req, timeout=10).status
            except urllib.error.HTTPError as exc:
                return exc.code
        assert post({"kind": "accept"}, token="guess") == 403
        assert post({"kind": "accept"}, host="evil.example:80") == 403
        assert post({"kind": "choose", "mode": "sport"}) == 400
        assert post({"kind": "launch"}) == 400
        assert not node.queued
        assert post({"kind": "choose", "mode": "safety"}) == 200
        assert post({"kind": "refuse"}) == 200
        assert list(node.queued) == [("choose", MODE_NAMES.index("safety")), ("refuse", None)]
    finally:
        web.stop()
    time.sleep(0.1)


def test_hil_run_refuses_an_interactive_driver_with_a_way_out(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "hil", "run", "--driver", "interactive",
                           "--out", str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    assert "--driver web" in proc.stderr
