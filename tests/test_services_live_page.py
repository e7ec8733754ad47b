"""The live drive page of `virtualaxis serve --http` (docs/live-page.md), through the user's doors: the page in
headless Chromium (Chrome DevTools Protocol), an HTTP client, a canopen master on the bus of the served drive."""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import re
import socket
import subprocess
import threading
import time
import urllib.request
from pathlib import Path

import canopen
import numpy as np
import pytest
from cdp_browser import CHROMIUM, Browser, wait_for_file
from served_drive import CLI, ROOT, children, served

from virtualaxis.master import LockstepMaster, connect

NODE = 1
AXIS = "seed000-hust"
CONFIG = "configs/seed000-hust.toml"


def page_url(s) -> str:
    """The page address `serve` prints after its ready line (``--http 127.0.0.1:0``: a free port)."""
    for _ in range(20):
        line = s.proc.stdout.readline()
        m = re.match(r"http: live page at (http://\S+/)", line)
        if m:
            return m.group(1)
    raise AssertionError("serve printed no 'http:' line")


def request(url: str, method: str = "GET", body: bytes | None = None, ctype: str = "application/json"):
    """(status, decoded JSON or text) of one request."""
    u = urllib.parse.urlsplit(url)
    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=20)
    conn.request(method, u.path + (f"?{u.query}" if u.query else ""), body=body,
                 headers={"Content-Type": ctype} if body is not None else {})
    r = conn.getresponse()
    data = r.read()
    conn.close()
    try:
        return r.status, json.loads(data)
    except ValueError:
        return r.status, data.decode("utf-8", "replace")


def raw_request(url: str, raw: bytes) -> tuple[int, dict]:
    u = urllib.parse.urlsplit(url)
    with socket.create_connection((u.hostname, u.port), timeout=10) as sock:
        sock.sendall(raw)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split(b" ")[1]), json.loads(body)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (Debian: apt-get install chromium; .ci/run "
                    "installs it)")
def test_page_in_chromium_follows_enable_csp_move_fault_and_records_a_trace(tmp_path):
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    with served("--lockstep", "--http", "127.0.0.1:0", "--allow-fault-injection") as s:
        url = page_url(s)
        net = connect(s.spec)
        try:
            with Browser.launch(downloads) as browser:
                tab = browser.open(url)
                tab.wait_for("window.livePage && window.livePage.stateMessages > 0")
                assert tab.text("#cia402-state") == "SWITCH ON DISABLED"
                assert tab.text("#nmt-state") == "PRE-OPERATIONAL"
                with LockstepMaster(net, [NODE], mode="csp") as m:  # PDOs by SDO, NMT start, enable
                    tab.wait_for("document.querySelector('#cia402-state').textContent === 'OPERATION ENABLED'")
                    assert tab.text("#nmt-state") == "OPERATIONAL"
                    assert tab.evaluate("document.querySelector('#sw-bits li[data-bit=\"2\"]').className") == "on"
                    rec = _move_and_record(tab, m, downloads)
                    _pause_zoom_and_cursors(tab, m, url, rec)
                    _trigger_on_threshold_and_statusword_bit(tab, m, url)
                    _trigger_on_injected_fault(tab, m)
        finally:
            net.disconnect()


def _move_and_record(tab, m: LockstepMaster, downloads: Path) -> dict:
    x0 = m.position_m(NODE)
    n_move, n_hold, stroke_m = 600, 150, 0.010
    ramp = (1 - np.cos(np.pi * np.arange(n_move) / (n_move - 1))) / 2
    setpoints = x0 + stroke_m * np.concatenate([ramp, np.ones(n_hold)])
    tab.wait_for("window.livePage.lastSeq >= 0")
    tab.click("#rec")
    seq_before = tab.evaluate("window.livePage.rec.from")
    shot = os.environ.get("VIRTUALAXIS_LIVE_PAGE_SCREENSHOT")  # docs/img/live-page.png is taken this way
    moved = threading.Thread(target=m.run, args=(setpoints,), daemon=True)
    moved.start()
    if shot:
        tab.wait_for("window.livePage.lastState && window.livePage.lastState.position_actual_m > "
                     f"{x0 + 0.6 * stroke_m}", timeout_s=60)
        tab.screenshot(shot)
    moved.join(120)
    assert not moved.is_alive()
    last = m.syncs
    # the scope shows the move: every drive cycle reached the page, in order, and the plotted positions span it
    tab.wait_for(f"window.livePage.lastState.cycles >= {last} && window.livePage.lastSeq + 1 >= "
                 f"window.livePage.lastState.ring.written")
    time.sleep(0.3)
    assert tab.evaluate("window.livePage.gaps") == 0
    pos_cmd_mm = tab.evaluate("window.livePage.charts[0].data[1]")
    pos_fb_mm = tab.evaluate("window.livePage.charts[0].data[2]")
    assert min(pos_cmd_mm) == pytest.approx(x0 * 1e3, abs=1e-3)
    assert max(pos_cmd_mm) == pytest.approx((x0 + stroke_m) * 1e3, abs=1e-3)
    assert pos_fb_mm[-1] == pytest.approx((x0 + stroke_m) * 1e3, abs=0.01)  # settled at the end of the hold
    fe_um = tab.evaluate("window.livePage.charts[1].data[1]")
    assert max(abs(v) for v in fe_um) > 1.0  # a lag while moving ...
    assert abs(fe_um[-1]) < 1.0  # ... gone at rest
    # the recording: every drive cycle between Record and Stop, a trace `virtualaxis diagnose` reads
    tab.click("#rec")
    rec = tab.evaluate("window.livePage.rec")
    assert rec["from"] == seq_before and rec["to"] - rec["from"] >= n_move + n_hold
    href = tab.evaluate("document.querySelector('#rec-download').href")
    st, body = request(href)
    assert st == 200, body  # (what the link downloads)
    tab.click("#rec-download")
    path = wait_for_file(downloads, ".csv", timeout_s=120)  # (the trace formatter compiles on its first use)
    from virtualaxis.diagnosis.trace import read_trace

    diag = subprocess.run([*CLI, "diagnose", "--config", CONFIG, str(path), "--out", str(downloads / "report"),
                           "--effects", "coulomb_friction", "--no-hybrid", "--jobs", "1"],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert diag.returncode == 0, diag.stderr
    assert json.loads((downloads / "report" / "report.json").read_text())
    trace = read_trace(path)
    assert len(trace.t) == rec["to"] - rec["from"]
    assert np.allclose(np.diff(trace.t), 1e-3)
    data = np.genfromtxt(path, delimiter=",", names=True)
    assert data["pos_cmd"].max() == pytest.approx(x0 + stroke_m, abs=1e-6)
    assert data["pos_fb"][-1] == pytest.approx(x0 + stroke_m, abs=1e-5)
    # the demand of every cycle: the master's set-points (one per SYNC), in the order sent
    demand = data["pos_cmd"]
    moving = demand[(demand > x0 + 1e-6) & (demand < x0 + stroke_m - 1e-6)]
    assert len(moving) >= n_move - 30 and np.all(np.diff(moving) >= -1e-9)
    return rec


def _plot_box(tab, chart: int = 0) -> list[float]:
    """[left, top, width, height] of a plot's drawing area in the viewport [CSS px], scrolled into view."""
    return tab.evaluate(f"(() => {{ const o = window.livePage.charts[{chart}].over; o.scrollIntoView({{block: "
                        "'center'}); const r = o.getBoundingClientRect(); "
                        "return [r.left, r.top, r.width, r.height]; })()")


def _x_of_sample(tab, seq: int, chart: int = 0) -> float:
    """The plot's x position [CSS px, from its drawing area's left] of sample ``seq`` (its time from the
    received scope messages)."""
    return tab.evaluate(f"(() => {{ const s = {seq}, c = window.livePage.chunks.find((c) => s >= c.seq0 && s < "
                        f"c.seq0 + c.n); return window.livePage.charts[{chart}].valToPos(c.t0 + (s - c.seq0) * c.dt, "
                        "'x'); })()")


def _pause_zoom_and_cursors(tab, m: LockstepMaster, url: str, rec: dict) -> None:
    """Pause holds the view while samples arrive; a drag zooms every plot to the samples of the dragged time
    window; two clicks place cursors A and B on samples, and the page's Δt / Δy are those of the server's
    recording of the same samples; a double click returns; Run follows the drive again."""
    last_t = "window.livePage.charts[0].data[0][window.livePage.charts[0].data[0].length - 1]"
    tab.click("#pause")
    assert tab.evaluate("window.livePage.paused") is True and tab.text("#pause") == "Run"
    shown_t, seq = tab.evaluate(f"[{last_t}, window.livePage.lastSeq]")
    for _ in range(100):
        m.step_raw()
    tab.wait_for(f"window.livePage.lastSeq >= {seq + 100}")
    time.sleep(0.2)  # (a few animation frames)
    assert tab.evaluate(last_t) == shown_t  # held
    full = tab.evaluate("[window.livePage.charts[0].scales.x.min, window.livePage.charts[0].scales.x.max]")
    # zoom: drag across the position plot from sample a to sample b of the move
    left, top, width, height = _plot_box(tab)
    a, b = rec["from"] + 200, rec["from"] + 420
    y = top + height / 2
    tab.drag(left + _x_of_sample(tab, a), y, left + _x_of_sample(tab, b), y)
    tab.wait_for("window.livePage.zoomed === true")
    zoom = tab.evaluate("window.livePage.charts.map((u) => [u.scales.x.min, u.scales.x.max, u.data[0].length])")
    view = tab.evaluate("window.livePage.view")
    assert abs(view[0] - a) <= 2 and abs(view[1] - 1 - b) <= 2, (view, a, b)  # the dragged window ...
    times = tab.evaluate(f"(() => {{ const r = []; for (let s = {view[0]}; s < {view[1]}; s++) {{ const c = window."
                         "livePage.chunks.find((c) => s >= c.seq0 && s < c.seq0 + c.n); r.push(c.t0 + (s - c.seq0) * "
                         "c.dt); } return r; })()")
    for x_min, x_max, n in zoom:  # ... on every plot: its x axis spans the window's samples, each one drawn
        assert (x_min, x_max, n) == pytest.approx((times[0], times[-1], len(times)), abs=1e-9)
    assert times[-1] - times[0] < 0.5 * (full[1] - full[0])
    # cursors: a click on sample ca, then on sample cb
    ca, cb = a + 40, a + 150
    for seq in (ca, cb):  # (the plot's place read before each click: the first cursor's readout may move it)
        left, top, width, height = _plot_box(tab)
        y = top + height / 2
        tab.click_at(left + _x_of_sample(tab, seq), y)
    readout = tab.evaluate("window.livePage.cursorReadout")
    # each cursor sits on the clicked sample; a neighbour is accepted, as the mouse event's position is
    # rounded to whole CSS pixels (a sample is a few px wide here) and uPlot's plot rectangle is its own cache
    assert abs(readout["a"]["seq"] - ca) <= 1 and abs(readout["b"]["seq"] - cb) <= 1, (readout, ca, cb)
    ca, cb = readout["a"]["seq"], readout["b"]["seq"]
    shown = tab.text("#cursor-info")
    dt_ms = float(re.search(r"Δt = (-?[\d.]+) ms", shown).group(1))
    dy = {name: float(v) for name, v in re.findall(r"(position demand|position actual|following error) "
                                                     r"(-?[\d.e+-]+) (?:mm|um)", shown)}
    st, csv = request(url + f"api/axes/{AXIS}/recording.csv?from={ca}&to={cb + 1}")
    assert st == 200
    lines = csv.strip().splitlines()
    head = lines[0].split(",")
    first, last = (dict(zip(head, map(float, row.split(",")), strict=True)) for row in (lines[1], lines[-1]))
    assert dt_ms == pytest.approx((last["t"] - first["t"]) * 1e3, abs=1e-3)
    assert dt_ms == pytest.approx((cb - ca) * 1.0, abs=1e-3)  # one sample per 1 ms drive cycle
    assert dy["position demand"] == pytest.approx((last["pos_cmd"] - first["pos_cmd"]) * 1e3, abs=1e-4)
    assert dy["position actual"] == pytest.approx((last["pos_fb"] - first["pos_fb"]) * 1e3, abs=1e-4)
    assert dy["following error"] == pytest.approx(
        (last["following_error"] - first["following_error"]) * 1e6, abs=1e-2)
    assert abs(dy["position demand"]) > 1.0  # (the window is inside the move)
    # a double click returns to the whole view; Run follows the drive again
    tab.click_at(left + width / 2, y, clicks=2)
    tab.wait_for("window.livePage.zoomed === false")
    back = tab.evaluate("[window.livePage.charts[0].scales.x.min, window.livePage.charts[0].scales.x.max]")
    assert back == pytest.approx(full, abs=1e-9)
    tab.click("#pause")
    seq = tab.evaluate("window.livePage.lastSeq")
    for _ in range(50):
        m.step_raw()
    tab.wait_for(f"window.livePage.lastSeq >= {seq + 50} && {last_t} > {back[1]}")


def _recorded(url: str, first: int, end: int) -> dict[str, np.ndarray]:
    """Samples first..end-1 as the server's recording gives them (a trace CSV), by column."""
    st, csv = request(url + f"api/axes/{AXIS}/recording.csv?from={first}&to={end}")
    assert st == 200, csv
    lines = csv.strip().splitlines()
    rows = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    return {c: rows[:, j] for j, c in enumerate(lines[0].split(","))}


def _arm(tab, mode: str, **fields: str) -> None:
    """Choose a trigger on the page (span 0.5 s) and arm it."""
    sets = "".join(f"document.querySelector('#{k.replace('_', '-')}').value = {json.dumps(v)};"
                   for k, v in fields.items())
    tab.evaluate(f"document.querySelector('#span').value = '0.5'; document.querySelector('#trig-mode').value = "
                 f"'{mode}'; document.querySelector('#trig-mode').onchange(); {sets}")
    tab.click("#trig-arm")
    assert tab.text("#trigger-status") == f"armed ({mode})"


def _held_at(tab) -> int:
    """The sample a fired trigger holds the view on (the page's ``triggered at ... (sample N)``)."""
    tab.wait_for("window.livePage.paused === true", timeout_s=30)
    assert tab.text("#trigger-status").startswith("triggered at")
    return int(tab.evaluate("document.querySelector('#trigger-status').dataset.seq"))


def _trigger_on_threshold_and_statusword_bit(tab, m: LockstepMaster, url: str) -> None:
    """A threshold trigger holds on the first sample above the level, a statusword-bit trigger on the first with
    the bit set, both read against the server's recording of the samples around it."""
    x0 = m.position_m(NODE)
    ramp = (1 - np.cos(np.pi * np.arange(300) / 299)) / 2
    level_mm = x0 * 1e3 + 1.0137
    _arm(tab, "threshold", trig_chan="pos_cmd", trig_level=str(level_mm))
    m.run(x0 + 0.002 * np.concatenate([ramp, np.ones(400)]))
    seq = _held_at(tab)
    pos_cmd_mm = _recorded(url, seq - 1, seq + 1)["pos_cmd"] * 1e3
    assert pos_cmd_mm[0] <= level_mm < pos_cmd_mm[1], (seq, pos_cmd_mm, level_mm)
    # bit 10 (target reached): it falls while the axis moves back and rises once it has settled
    _arm(tab, "bit", trig_bit="10")
    first = tab.evaluate("window.livePage.lastSeq") + 1
    m.run(x0 + 0.002 * np.concatenate([1 - ramp, np.zeros(700)]))
    seq = _held_at(tab)
    sw = _recorded(url, first, seq + 1)["statusword"].astype(int)
    bit = (sw >> 10) & 1
    assert bit[-2:].tolist() == [0, 1] and 0 in bit[:-1], (seq, bit)
    assert not np.any((bit[1:-1] == 1) & (bit[:-2] == 0))  # no earlier rising edge


def _trigger_on_injected_fault(tab, m: LockstepMaster) -> None:
    tab.evaluate("document.querySelector('#span').value = '0.5'; document.querySelector('#trig-mode').value = 'fault';"
                 "document.querySelector('#trig-mode').onchange()")
    tab.click("#trig-arm")
    assert tab.text("#trigger-status") == "armed (fault)"
    for _ in range(50):
        m.step_raw()
    tab.click('button[data-kind="over_current"]')
    tab.wait_for("document.querySelector('#inject-result').textContent.includes('ok')")
    for _ in range(450):  # the cycles after the fault: the trigger holds the view once 70 % of the span followed
        m.step_raw()
    tab.wait_for("window.livePage.paused === true", timeout_s=20)
    status = tab.text("#trigger-status")
    assert status.startswith("triggered at")
    seq = int(tab.evaluate("document.querySelector('#trigger-status').dataset.seq"))
    sw = tab.evaluate(f"(() => {{ const r = []; for (const s of [{seq - 1}, {seq}]) {{ const c = window.livePage."
                      f"chunks.find((c) => s >= c.seq0 && s < c.seq0 + c.n); r.push(c.data[(s - c.seq0) * c.cols + "
                      f"c.cols - 1]); }} return r; }})()")
    assert (int(sw[0]) & 0x8, int(sw[1]) & 0x8) == (0, 0x8)  # the first cycle with the fault bit
    tab.wait_for("document.querySelector('#cia402-state').textContent === 'FAULT'")
    assert "0x2310" in tab.text("#faults")
    assert "0x2310" in tab.text("#bus-events")  # the EMCY frame the drive sent


def test_writes_answer_as_sdo_and_bad_requests_change_nothing():
    with served("--http", "127.0.0.1:0", "--http-writable") as s:
        url = page_url(s)
        api = url + f"api/axes/{AXIS}"
        net = canopen.Network()
        net.connect(**s.bus_kwargs())
        try:
            node = canopen.RemoteNode(NODE, "eds/virtualaxis.eds")
            net.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 5.0
            # a write through the page is what an SDO upload then reads
            st, body = request(api + "/write", "POST",
                               json.dumps({"index": "0x6081", "sub": 0, "value": 4321}).encode())
            assert (st, body["value"]) == (200, 4321)
            assert node.sdo.upload(0x6081, 0) == (4321).to_bytes(4, "little")
            # refused writes: the abort code an SDO download of the same value gets
            cases = [(0x6041, 0, 1), (0x7777, 0, 1), (0x1003, 0, 5), (0x1003, 0, 9), (0x6060, 0, 99),
                     (0x2000, 0, 1999.0), (0x6081, 7, 1)]
            for index, sub, value in cases:
                st, body = request(api + "/write", "POST",
                                   json.dumps({"index": index, "sub": sub, "value": value}).encode())
                fmt = "<f" if isinstance(value, float) else ("<B" if index in (0x1003,) else "<b" if index == 0x6060
                                                               else "<I")
                import struct

                with pytest.raises(canopen.SdoAbortedError) as sdo:
                    node.sdo.download(index, sub, struct.pack(fmt, value))
                assert st == 422, (index, body)
                assert body["abort_code"] == f"0x{sdo.value.code:08X}", (index, sub, value, body)
            before = request(api + "/objects")[1]["objects"]
            bad = [
                b"GARBAGE\r\n\r\n",
                b"GET / HTTP/9.9\r\n\r\n",
                b"\xff\xfe / HTTP/1.1\r\n\r\n",
                b"GET /" + b"a" * 5000 + b" HTTP/1.1\r\n\r\n",
                b"DELETE /api/axes HTTP/1.1\r\n\r\n",
                b"GET /api/axes HTTP/1.1\r\nno colon here\r\n\r\n",
                f"POST /api/axes/{AXIS}/write HTTP/1.1\r\nContent-Length: 99999\r\n\r\n".encode(),
                f"POST /api/axes/{AXIS}/write HTTP/1.1\r\n\r\n".encode(),
                f"POST /api/axes/{AXIS}/write HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n".encode(),
                f"GET /api/axes/{AXIS}/events HTTP/1.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\r\n".encode(),
                f"GET /api/axes/{AXIS}/recording.csv?from=5&to=2 HTTP/1.1\r\n\r\n".encode(),
                f"GET /api/axes/{AXIS}/recording.csv?from=0&to=99999999999 HTTP/1.1\r\n\r\n".encode(),
                f"GET /api/axes/{AXIS}/recording.csv?from=-1&to=2 HTTP/1.1\r\n\r\n".encode(),
                b"GET /api/axes/nope/objects HTTP/1.1\r\n\r\n",
                b"GET /static/../server.py HTTP/1.1\r\n\r\n",
            ]
            for body_text in [b"{", b"[]", b'{"index": "0x6081", "sub": 0}', b'{"index": "0x6081", "value": NaN}',
                              b'{"index": true, "value": 1}', b'{"index": "0x6081", "value": 1, "value": 2}',
                              b'{"index": "0x6081", "value": "fast"}', b'{"index": "0x6081", "value": 1, "x": 0}',
                              b'{"index": "0x6081", "value": 1.5}', b"\xff\xfe", b'{"index": "0x16081", "value": 1}']:
                bad.append(f"POST /api/axes/{AXIS}/write HTTP/1.1\r\nContent-Type: application/json\r\n"
                           f"Content-Length: {len(body_text)}\r\n\r\n".encode() + body_text)
            for raw in bad:
                st, body = raw_request(url, raw)
                assert 400 <= st < 600 and isinstance(body.get("error"), str) and body["error"], (raw[:60], st, body)
            after = request(api + "/objects")[1]["objects"]
            values = lambda objs: {(o["index"], o["sub"]): o.get("value") for o in objs  # noqa: E731
                                   if o["access"] in ("rw", "wo", "rwr", "rww")}
            assert values(after) == values(before)
            assert node.sdo.upload(0x6081, 0) == (4321).to_bytes(4, "little")
            st, info = request(url + "api/axes")
            assert st == 200 and info["writable"] is True
        finally:
            net.disconnect()
        assert s.stop() == 0
        assert "Traceback" not in s.stderr


def _ws_open(url: str, path: str) -> socket.socket:
    """A raw WebSocket handshake on ``path``; the socket after the 101 answer."""
    u = urllib.parse.urlsplit(url)
    sock = socket.create_connection((u.hostname, u.port), timeout=10)
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: {u.netloc}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101") and b"s3pPLMBiTxaQ9kYGzzhZRbK+xOo=" in head, head
    return sock


def _ws_read(sock: socket.socket) -> tuple[int, bytes]:
    def exact(n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    b0, b1 = exact(2)
    n = b1 & 0x7F
    if n == 126:
        n = int.from_bytes(exact(2), "big")
    elif n == 127:
        n = int.from_bytes(exact(8), "big")
    return b0 & 0x0F, exact(n)


def _ws_frame(opcode: int, payload: bytes, *, masked: bool = True, rsv: int = 0, length: int | None = None) -> bytes:
    n = len(payload) if length is None else length
    head = bytes((0x80 | rsv | opcode,)) + (bytes(((0x80 if masked else 0) | n,)) if n < 126 else
                                            bytes(((0x80 if masked else 0) | 126,)) + n.to_bytes(2, "big"))
    if not masked:
        return head + payload
    mask = b"\x01\x02\x03\x04"
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def test_websocket_sends_live_updates_and_refuses_what_it_does_not_take():
    with served("--http", "127.0.0.1:0", "--http-writable") as s:
        url = page_url(s)
        path = f"/api/axes/{AXIS}/live"
        sock = _ws_open(url, path)
        events = set()
        while not {"state", "scope"} <= events:
            op, data = _ws_read(sock)
            assert op == 0x1
            events.add(json.loads(data)["event"])
        # a data message: an error message back, the socket stays open
        sock.sendall(_ws_frame(0x1, b'{"index": "0x6081", "value": 1}'))
        while True:
            op, data = _ws_read(sock)
            msg = json.loads(data)
            if msg["event"] == "error":
                assert "only sends" in msg["data"]["error"]
                break
        sock.sendall(_ws_frame(0x9, b"hi"))
        while (got := _ws_read(sock))[0] != 0xA:
            pass
        assert got[1] == b"hi"
        sock.close()
        # frames that break the protocol: closed with 1002 / 1009 and a reason
        for frame, code in [(_ws_frame(0x1, b"{}", masked=False), 1002), (_ws_frame(0x1, b"{}", rsv=0x40), 1002),
                            (_ws_frame(0x3, b"{}"), 1002), (_ws_frame(0x9, b"x" * 126), 1002),
                            (_ws_frame(0x1, b"", length=5000), 1009)]:
            sock = _ws_open(url, path)
            sock.sendall(frame)
            while (got := _ws_read(sock))[0] != 0x8:
                pass
            assert int.from_bytes(got[1][:2], "big") == code and got[1][2:], (frame[:4], got)
            sock.close()
        # handshakes that are not: refused with a clear answer
        for raw in [f"GET {path} HTTP/1.1\r\n\r\n",
                    f"GET {path} HTTP/1.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                    "Sec-WebSocket-Key: short\r\nSec-WebSocket-Version: 13\r\n\r\n",
                    f"GET {path} HTTP/1.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                    "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 8\r\n\r\n"]:
            st, body = raw_request(url, raw.encode())
            assert st == 400 and body["error"], raw
        st, body = request(url + f"api/axes/{AXIS}/objects")
        assert st == 200
        assert {(o["index"], o["sub"]): o.get("value") for o in body["objects"]}[("0x6081", 0)] != 1
        s.stop()
        assert "Traceback" not in s.stderr


def test_at_real_time_priority_the_state_messages_are_made_in_the_runtime_threads_gap(tmp_path):
    """serve --rt-priority: the page's state messages are made by the runtime thread in the gap before a drive
    cycle (serve's JSON counts them as gap jobs), not by a thread that would hold the interpreter lock while the
    drive's thread waits; they still come ten times a second, each with the drive's time advanced."""
    out = tmp_path / "serve.json"
    try:
        cm = served("--http", "127.0.0.1:0", "--rt-priority", "5", "--json", str(out))
        s = cm.__enter__()
    except AssertionError as exc:
        if "SCHED_FIFO" in str(exc):
            pytest.skip("SCHED_FIFO not permitted on this host")
        raise
    try:
        sock = _ws_open(page_url(s), f"/api/axes/{AXIS}/live")
        cycles: list[int] = []
        t_end = time.monotonic() + 2.0
        while time.monotonic() < t_end:
            op, data = _ws_read(sock)
            msg = json.loads(data)
            if op == 0x1 and msg["event"] == "state":
                cycles.append(msg["data"]["cycles"])
        sock.close()
    finally:
        cm.__exit__(None, None, None)
    # (the page's server sends the newest state at its own pace: one serve has not replaced yet comes twice)
    assert all(b >= a for a, b in zip(cycles, cycles[1:], strict=False)), cycles
    assert len({c for c in cycles if c > 0}) >= 10, cycles  # 10 new ones per second with a stream open
    runtime = json.loads(out.read_text())["runtime"]
    assert runtime["gap_jobs"] >= len(cycles) - 1 and runtime["gap_job_errors"] == 0, runtime


def test_read_only_page_refuses_writes_and_fault_injection():
    with served("--http", "127.0.0.1:0") as s:
        api = page_url(s) + f"api/axes/{AXIS}"
        st, body = request(api + "/write", "POST", b'{"index": "0x6081", "sub": 0, "value": 4321}')
        assert st == 403 and "--http-writable" in body["error"]
        st, body = request(api + "/fault", "POST", b'{"action": "inject", "kind": "over_current"}')
        assert st == 403 and body["abort_code"] == "0x08000022"
        st, objs = request(api + "/objects")
        assert {(o["index"], o["sub"]): o.get("value") for o in objs["objects"]}[("0x6081", 0)] != 4321
        st, info = request(api.rsplit("/", 1)[0])
        assert info["writable"] is False and info["axes"][0]["fault_injection"] is False


def _stream(url: str, seconds: float, out: dict) -> None:
    """Read one event stream for ``seconds``: scope sequence numbers and state messages."""
    u = urllib.parse.urlsplit(url)
    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=10)
    conn.request("GET", u.path)
    r = conn.getresponse()
    out["status"] = r.status
    end = time.monotonic() + seconds
    event = None
    while time.monotonic() < end:
        line = r.fp.readline().decode()
        if line.startswith("event: "):
            event = line[7:].strip()
        elif line.startswith("data: "):
            msg = json.loads(line[6:])
            if event == "scope":
                out.setdefault("scope", []).append((msg["seq0"], msg["n"]))
            elif event == "state":
                out["states"] = out.get("states", 0) + 1
    conn.close()


def _live(url: str, axis: str, seconds: float, out: dict) -> None:
    """Read one axis's WebSocket for ``seconds`` as the page does: scope sequence numbers (each message's samples
    decoded) and state messages."""
    import base64

    sock = _ws_open(url, f"/api/axes/{axis}/live")
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            op, data = _ws_read(sock)
            msg = json.loads(data)
            if msg["event"] == "scope":
                d = msg["data"]
                assert len(base64.b64decode(d["b64"])) == 4 * d["n"] * d["cols"]
                out.setdefault("scope", []).append((d["seq0"], d["n"]))
            elif msg["event"] == "state":
                out["states"] = out.get("states", 0) + 1
    finally:
        sock.close()


def test_ten_tabs_on_three_axes_get_every_cycle():
    """Ten clients on three axes, eight on the page's WebSocket (as eight tabs), two on the event stream: each gets
    every drive cycle's samples, in order, and the state messages."""
    axes = [f"--axis=X=1:{CONFIG}", f"--axis=Y=2:{CONFIG}", f"--axis=Z=3:{CONFIG}"]
    with served(*axes, "--http", "127.0.0.1:0") as s:
        url = page_url(s)
        outs = [{} for _ in range(10)]
        threads = [threading.Thread(target=_live, args=(url, "XYZ"[i % 3], 3.0, outs[i])) if i % 5 else
                   threading.Thread(target=_stream, args=(f"{url}api/axes/{'XYZ'[i % 3]}/events", 3.0, outs[i]))
                   for i in range(10)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        for i, out in enumerate(outs):
            assert out.get("status", 200) == 200 and out.get("states", 0) >= 10, (i, out.get("states"))
            chunks = out["scope"]
            assert all(a + n == b for (a, n), (b, _) in zip(chunks, chunks[1:], strict=False)), i  # contiguous
            assert sum(n for _, n in chunks) > 300, i  # (real time: ~1000 cycles/s on an idle host)
        s.stop()
        assert "Traceback" not in s.stderr


def test_http_option_errors_are_one_line(tmp_path):
    """A page address in use ends `serve` with one error line naming it, exit 2; bad values are refused before the
    bus opens, naming the option."""
    import argparse

    from virtualaxis.services.serve_options import add_arguments, prepare

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        r = subprocess.run([*CLI, "serve", "--can", "udp_multicast:239.74.163.12,port=43918", "--duration", "1",
                            "--status-interval", "0", "--http", f"127.0.0.1:{port}"],
                           capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(f"error: --http 127.0.0.1:{port}: cannot listen"), r.stderr
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    for argv, expect in [(["--http", "127.0.0.1:abc"], "--http '127.0.0.1:abc': port 'abc' is not a number"),
                         (["--http", "127.0.0.1:70000"], "port must be 0..65535"),
                         (["--http", "8080"], "expected HOST:PORT"),
                         (["--http", "999.1.1.1:8080"], "--http 999.1.1.1:8080: cannot resolve"),
                         (["--http", "192.0.2.1:8080"], "--http 192.0.2.1:8080: cannot listen"),
                         (["--http-writable"], "--http-writable needs --http")]:
        with pytest.raises(ValueError) as exc:
            prepare(parser.parse_args(argv), CONFIG)
        assert expect in str(exc.value), (argv, str(exc.value))


def _listening_pids(port: int, pids: list[int]) -> set[int]:
    """Those of ``pids`` that hold the TCP socket listening on ``port`` (from /proc: its inode among their fds)."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for line in f.readlines()[1:]:
                fields = line.split()
                if int(fields[1].rsplit(":", 1)[1], 16) == port and fields[3] == "0A":  # 0A: LISTEN
                    inodes.add(f"socket:[{fields[9]}]")
    assert inodes, f"nothing listens on port {port}"
    owners = set()
    for pid in pids:
        with contextlib.suppress(OSError):
            for fd in os.listdir(f"/proc/{pid}/fd"):
                with contextlib.suppress(OSError):
                    if os.readlink(f"/proc/{pid}/fd/{fd}") in inodes:
                        owners.add(pid)
    return owners


def test_page_server_is_a_child_process_whose_end_leaves_the_drive_cycling():
    """The page's socket belongs to a child process of serve, not to serve; killing that process is reported on
    serve's stderr, and the drive goes on cycling and answering on the bus."""
    import signal

    with served("--http", "127.0.0.1:0") as s:
        url = page_url(s)
        port = urllib.parse.urlsplit(url).port
        kids = children(s.proc.pid)
        owners = _listening_pids(port, [s.proc.pid, *kids])
        assert len(owners) == 1 and s.proc.pid not in owners, (s.proc.pid, kids, owners)
        (server_pid,) = owners
        st, info = request(url + "api/axes")
        assert st == 200 and info["axes"][0]["name"] == AXIS
        net = canopen.Network()
        net.connect(**s.bus_kwargs())
        try:
            node = canopen.RemoteNode(NODE, "eds/virtualaxis.eds")
            net.add_node(node)
            node.sdo.RESPONSE_TIMEOUT = 5.0
            os.kill(server_pid, signal.SIGKILL)
            lines: list[str] = []
            reader = threading.Thread(target=lambda: lines.append(s.proc.stderr.readline()), daemon=True)
            reader.start()
            reader.join(20)
            assert lines and lines[0].startswith("warning: --http: the live page's server process ended"), lines
            cycles = []
            for _ in range(2):
                cycles.append(int.from_bytes(node.sdo.upload(0x2110, 5), "little"))
                time.sleep(0.5)
            assert cycles[1] - cycles[0] > 200, cycles  # (real time: ~500 cycles of 1 ms in 0.5 s)
            assert int.from_bytes(node.sdo.upload(0x2110, 6), "little") == 0  # no exception in the cycle
            with pytest.raises(OSError):
                request(url + "api/axes")
        finally:
            net.disconnect()
        assert s.stop() == 0
        assert "Traceback" not in s.stderr, s.stderr


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie waiting for its reaper does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_page_server_process_ends_with_a_killed_serve():
    """No orphan: the page's server process ends when serve is killed (SIGKILL: serve cleans nothing up)."""
    import signal

    with served("--http", "127.0.0.1:0") as s:
        port = urllib.parse.urlsplit(page_url(s)).port
        (server_pid,) = _listening_pids(port, children(s.proc.pid))
        os.kill(s.proc.pid, signal.SIGKILL)
        s.proc.wait(10)
        deadline = time.monotonic() + 10
        while _alive(server_pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(server_pid), f"the page's server process {server_pid} outlived serve"


def test_ring_counts_what_the_server_fell_too_far_behind_for():
    """The shared sample ring: every cycle's values in SI units, in order; when the server process falls more than
    the ring's slots behind, the overwritten samples are counted lost and a recording over them is refused."""
    from types import SimpleNamespace

    from virtualaxis.services.http.ring import (
        HANDOFF_MARGIN,
        HANDOFF_SLOTS,
        LongRing,
        PageBlock,
        RecordingError,
        segment_size,
    )

    buf = memoryview(bytearray(segment_size(2)))
    block = PageBlock(buf, 1)  # (the second axis' block: nothing of it may land in the first's)
    drive = SimpleNamespace(outputs=(None,) * 15, objects={(0x6041, 0): 0x250},
                            scaling=SimpleNamespace(metres_per_unit=1e-6), read_object=lambda index: 2000)
    block.set_units(drive)
    ring = LongRing(block, 1e-3, seconds=60.0)

    def cycles(first: int, n: int) -> None:
        for k in range(first, first + n):
            drive.outputs = (8, 10 * k, 0, 10 * k + 1, 0, 5, 500, -250, 0, 3, 0, 25.0, 0, k, 0)
            block.hook(drive)

    block.hook(drive)  # (before the drive published anything: a row of NaN, still one per cycle)
    cycles(0, 100)
    first, end = ring.drain()
    assert (first, end, ring.lost) == (0, 101, 0)
    times, rows = ring.slice(1, 101)
    assert np.allclose(rows[:, 0], 10e-6 * np.arange(100)) and np.allclose(rows[:, 1], 10e-6 * np.arange(100) + 1e-6)
    assert np.allclose(rows[:, 2], 3e-6) and np.allclose(rows[:, 3], 5e-6)
    assert np.allclose(rows[:, 4], 0.5 * 2.0) and np.allclose(rows[:, 5], -0.25 * 2.0)  # per mille of 2 N m, 2 A
    assert np.all(rows[:, 6] == 0x250) and np.allclose(np.diff(times), 1e-3)
    assert np.all(np.isnan(ring.slice(0, 1)[1][0, :6]))
    assert not buf[:len(buf) // 2].tobytes().strip(b"\x00")  # (the first axis' block untouched)
    # the server process away for more than the ring's slots: the oldest are lost, counted; the rest in order
    cycles(100, HANDOFF_SLOTS + 500)
    first, end = ring.drain()
    kept = HANDOFF_SLOTS - HANDOFF_MARGIN
    assert ring.lost == HANDOFF_SLOTS + 500 - kept and (first, end) == (101, 101 + kept)
    times, rows = ring.slice(first, end)
    k0 = 100 + ring.lost
    assert np.allclose(rows[:, 0], 10e-6 * np.arange(k0, k0 + kept))
    with pytest.raises(RecordingError, match="no longer held"):
        ring.slice(50, 150)  # (spans the lost samples)
    assert np.allclose(times, (np.arange(k0, k0 + kept) + 1) * 1e-3)  # (the drive's time: no gap closed up)
    block.set_state(b'{"axis": "X", "cycles": 7}')
    state = json.loads(ring.state_message())
    assert state["cycles"] == 7 and state["ring"]["lost"] == ring.lost and state["ring"]["written"] == end


def test_a_state_message_is_read_whole_or_the_one_before_while_serve_writes_the_next():
    """The server process reads an axis' state message while serve's writer replaces it: every read is a message
    written whole (the newest, or while one is being written the one read before), never a torn one."""
    from virtualaxis.services.http.ring import PageBlock, segment_size

    buf = memoryview(bytearray(segment_size(1)))
    writer, reader = PageBlock(buf, 0), PageBlock(buf, 0)
    messages = [json.dumps({"n": k, "pad": "x" * (k % 7) * 300}).encode() for k in range(50)]
    stop = threading.Event()

    def write() -> None:
        k = 0
        while not stop.is_set():
            writer.set_state(messages[k % len(messages)])
            k += 1

    assert reader.state() == b""
    writer.set_state(messages[0])
    assert reader.state() == messages[0]
    t = threading.Thread(target=write)
    t.start()
    try:
        reads = [reader.state() for _ in range(20_000)]
    finally:
        stop.set()
        t.join()
    whole = set(messages)
    assert all(r in whole for r in reads), next(r for r in reads if r not in whole)[:80]
    assert len(set(reads)) > 1  # (the writer did write meanwhile)
