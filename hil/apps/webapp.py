"""The driver app in a browser (the paper's "vehicle application"): an aiohttp server on
127.0.0.1, in a thread of the app node, serving one page that shows what the ECU recommends
(the mode, the estimated grade and why), the active mode, live BA and DTD RMS, the energy and
the ECU's faults by name, with buttons to accept or refuse the recommendation or choose a mode.
A click is queued to the app node (``AppNode.push``), which sends it as its next
DRIVER_REQUEST, SecOC-protected like every other: the page commands nothing else.

    GET  /        the page
    GET  /state   the driver's picture as JSON (``hil.apps.driver.describe``) and the requests sent
    POST /request {"kind": "accept" | "refuse" | "choose", "mode": "comfort"} with the page's
                  token in ``X-Driver-Token``; 400 on a bad request, 403 without the token

Only 127.0.0.1: the server binds there, answers only requests addressed to it (a page of
another site cannot reach it by DNS rebinding) and takes requests only with the per-run token
the page carries (another site's page cannot read it, nor send the header without it)."""

from __future__ import annotations

import asyncio
import json
import secrets
import threading
from typing import Optional

from aiohttp import web

from firmware.params import MODE_NAMES
from hil.apps.driver import describe, name_of

HOST = "127.0.0.1"


class WebApp:
    def __init__(self, node, port: int = 0):
        self.node, self.port = node, port
        self.token = secrets.token_urlsafe(16)
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._runner: Optional[web.AppRunner] = None
        self._thread: Optional[threading.Thread] = None
        self._bound = threading.Event()
        self._error: Optional[BaseException] = None

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}/"

    def start(self) -> str:
        """Serve in a daemon thread; returns the page's URL once bound. OSError when the port
        cannot be bound."""
        self._thread = threading.Thread(target=self._serve, name="webapp", daemon=True)
        self._thread.start()
        self._bound.wait(30)
        if self._error is not None:
            raise OSError(f"the driver page cannot listen on {HOST}:{self.port}: "
                          f"{self._error}") from self._error
        return self.url

    def stop(self) -> None:
        if self._loop is not None and self._runner is not None:
            fut = asyncio.run_coroutine_threadsafe(self._runner.cleanup(), self._loop)
            try:
                fut.result(5)
            except Exception:  # noqa: BLE001 - stopping anyway
                pass
            self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(5)

    # ------------------------------------------------------------------ server
    def _serve(self) -> None:
        self._loop = asyncio.new_event_loop()
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._bind())
        except BaseException as exc:  # noqa: BLE001 - reported by start()
            self._error = exc
            self._bound.set()
            return
        self._bound.set()
        self._loop.run_forever()
        self._loop.close()

    async def _bind(self) -> None:
        app = web.Application(middlewares=[self._only_here], client_max_size=4096)
        app.router.add_get("/", self._page)
        app.router.add_get("/state", self._state)
        app.router.add_post("/request", self._request)
        self._runner = web.AppRunner(app, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, HOST, self.port)
        await site.start()
        self.port = site._server.sockets[0].getsockname()[1]

    @web.middleware
    async def _only_here(self, request, handler):
        if request.host not in (f"{HOST}:{self.port}", f"localhost:{self.port}"):
            return web.json_response({"error": "not addressed to this page's host"}, status=403)
        return await handler(request)

    async def _page(self, _request):
        return web.Response(text=PAGE.replace("__TOKEN__", self.token),
                            content_type="text/html", charset="utf-8",
                            headers={"Cache-Control": "no-store"})

    async def _state(self, _request):
        node = self.node
        d = describe(dict(node.view), node.t * node.dt)
        d["sent"] = [{"t_s": round(t, 3), "kind": k, "mode": name_of(MODE_NAMES, m, m)}
                     for t, k, m in list(node.log)[-8:]]
        d["queued"] = len(node.queued)
        return web.json_response(d, headers={"Cache-Control": "no-store"})

    async def _request(self, request):
        if not secrets.compare_digest(request.headers.get("X-Driver-Token", ""), self.token):
            return web.json_response({"error": "no valid X-Driver-Token"}, status=403)
        try:
            body = json.loads(await request.text())
            kind = body["kind"]
            mode = body.get("mode")
            if kind not in ("accept", "refuse", "choose"):
                raise ValueError(f"kind {kind!r}: accept, refuse or choose")
            if kind == "choose" and mode not in MODE_NAMES:
                raise ValueError(f"mode {mode!r}: one of {', '.join(MODE_NAMES)}")
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            return web.json_response({"error": f"bad request: {exc}"}, status=400)
        self.node.push(kind, MODE_NAMES.index(mode) if kind == "choose" else None)
        return web.json_response({"queued": kind, "mode": mode})


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>Suspension: driver app</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
 body{font-family:system-ui,sans-serif;margin:0;background:#f4f5f7;color:#1d2330}
 header{background:#1d2330;color:#fff;padding:12px 20px;font-size:18px}
 main{display:grid;grid-template-columns:1fr 1fr;gap:16px;padding:16px 20px;max-width:980px}
 .card{background:#fff;border-radius:8px;padding:14px 18px;box-shadow:0 1px 3px #0002}
 .big{font-size:30px;font-weight:700;text-transform:capitalize}
 .why{color:#4a5263;margin-top:6px;min-height:2.4em}
 .override{color:#b3261e;font-weight:600}
 button{font-size:15px;padding:8px 14px;margin:4px 6px 0 0;border-radius:6px;border:1px solid #889;
        background:#fff;cursor:pointer;text-transform:capitalize}
 button.primary{background:#1a73e8;color:#fff;border-color:#1a73e8}
 table{border-collapse:collapse;width:100%} td{padding:3px 4px} td.v{text-align:right;font-variant-numeric:tabular-nums}
 .faults{color:#b3261e} .ok{color:#1e7d32} small{color:#667}
</style></head>
<body><header>Intelligent suspension &mdash; driver app <small id="clock"></small></header>
<main>
 <div class="card"><div>ECU recommends</div>
  <div class="big" id="recommended">&hellip;</div>
  <div class="why" id="why"></div>
  <div><button class="primary" id="accept">Accept</button><button id="refuse">Refuse</button></div>
 </div>
 <div class="card"><div>Active mode</div>
  <div class="big" id="active">&hellip;</div>
  <div class="why">estimated grade <b id="grade">?</b></div>
  <div id="choose"></div>
 </div>
 <div class="card"><table>
  <tr><td>speed</td><td class="v" id="speed"></td></tr>
  <tr><td>body acceleration RMS</td><td class="v" id="ba"></td></tr>
  <tr><td>tyre deflection RMS</td><td class="v" id="dtd"></td></tr>
  <tr><td>energy harvested</td><td class="v" id="stored"></td></tr>
  <tr><td>energy drawn from the supply</td><td class="v" id="drawn"></td></tr>
 </table></div>
 <div class="card"><div>ECU faults</div><div id="faults" class="ok">none</div>
  <div id="degraded" class="ok">all sensors in use</div>
  <div style="margin-top:8px"><small>Sent:</small> <small id="sent"></small></div>
  <div><small>DTCs with snapshots: <code>python -m hil diag</code></small></div></div>
</main>
<script>
const TOKEN = "__TOKEN__";
const $ = (id) => document.getElementById(id);
const fmt = (x, d, u) => (x === null || x === undefined) ? "&ndash;" : x.toFixed(d) + " " + u;
async function send(kind, mode) {
  const r = await fetch("request", {method: "POST", headers: {"Content-Type": "application/json",
    "X-Driver-Token": TOKEN}, body: JSON.stringify({kind: kind, mode: mode})});
  if (!r.ok) alert((await r.json()).error);
}
$("accept").onclick = () => send("accept");
$("refuse").onclick = () => send("refuse");
let built = false;
async function poll() {
  try {
    const s = await (await fetch("state")).json();
    if (!built) {
      for (const m of s.modes) {
        const b = document.createElement("button"); b.id = "choose-" + m; b.textContent = m;
        b.onclick = () => send("choose", m); $("choose").appendChild(b);
      }
      built = true;
    }
    $("clock").textContent = "t = " + s.t_s.toFixed(1) + " s";
    $("recommended").textContent = s.recommended || "\\u2026";
    $("why").textContent = s.why; $("why").className = s.override ? "why override" : "why";
    $("active").textContent = s.active || "\\u2026";
    $("grade").textContent = s.grade;
    $("speed").innerHTML = fmt(s.speed_mps, 1, "m/s");
    $("ba").innerHTML = fmt(s.ba_rms_mps2, 3, "m/s\\u00b2");
    $("dtd").innerHTML = fmt(s.dtd_rms_mm, 2, "mm");
    $("stored").innerHTML = fmt(s.stored_j, 2, "J");
    $("drawn").innerHTML = fmt(s.drawn_j, 2, "J");
    $("faults").textContent = s.faults.length ? s.faults.join(", ") : "none";
    $("faults").className = s.faults.length ? "faults" : "ok";
    $("degraded").textContent = s.degraded === "normal" ? "all sensors in use"
      : s.degraded === "fail_safe_latched" ? "fail-safe latched until the next start (read the DTCs)"
      : "one sensor out: driving on the others" + (s.degraded === "sensor_out_latched"
        ? " until the next start" : "") + " (read the DTCs)";
    $("degraded").className = s.degraded === "normal" ? "ok" : "faults";
    $("sent").textContent = s.sent.map(e => e.t_s.toFixed(1) + " s " + e.kind + " " + e.mode).join("; ")
      + (s.queued ? " (+" + s.queued + " queued)" : "");
  } catch (e) { $("why").textContent = "the app node is not answering (run over?)"; }
}
setInterval(poll, 250); poll();
</script></body></html>
"""
