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


def request(url: str, method: str = "GET", body: bytes | None = None, ctype: str = "application/json",
            timeout_s: float = 20.0):
    """(status, decoded JSON or text) of one request."""
    u = urllib.parse.urlsplit(url)
    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=timeout_s)
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
    status, _, body = raw_exchange(url, raw)
    return status, json.loads(body)


def raw_exchange(url: str, raw: bytes) -> tuple[int, dict[str, str], bytes]:
    """(status, headers by lower-case name, body) of the answer to the bytes ``raw`` sent as they are."""
    u = urllib.parse.urlsplit(url)
    with socket.create_connection((u.hostname, u.port), timeout=20) as sock:
        sock.sendall(raw)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
    return int(lines[0].split(" ")[1]), headers, body


def with_host(url: str, raw: bytes) -> bytes:
    """``raw`` with the Host header of ``url`` after its first line (HTTP/1.1 requires one)."""
    line, sep, rest = raw.partition(b"\r\n")
    return line + sep + f"Host: {urllib.parse.urlsplit(url).netloc}\r\n".encode() + rest


def post(url: str, path: str, body: bytes, headers: str = "Content-Type: application/json\r\n") -> tuple[int, dict]:
    """A POST of ``body`` with the Host of ``url`` and the header lines ``headers`` (raw: each ends with CRLF)."""
    return raw_request(url, f"POST {path} HTTP/1.1\r\nHost: {urllib.parse.urlsplit(url).netloc}\r\n{headers}"
                            f"Content-Length: {len(body)}\r\n\r\n".encode() + body)


def value_of(url: str, index: str, sub: int = 0):
    """The value of an object as the page's object list gives it."""
    st, body = request(url + f"api/axes/{AXIS}/objects")
    assert st == 200, body
    return {(o["index"], o["sub"]): o.get("value") for o in body["objects"]}[(index, sub)]


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (Debian: apt-get install chromium; .ci/run "
                    "installs it)")
def test_page_in_chromium_follows_enable_csp_move_fault_and_records_a_trace(tmp_path):
    downloads = tmp_path / "downloads"
    downloads.mkdir()
    with served("--lockstep", "--http", "127.0.0.1:0", "--http-writable", "--allow-fault-injection") as s:
        url = page_url(s)
        net = connect(s.spec)
        try:
            with Browser.launch(downloads) as browser:
                tab = browser.open(url)
                tab.wait_for("window.livePage && window.livePage.stateMessages > 0")
                # (the first state message may predate the node's boot-up: INITIALISING, then PRE-OPERATIONAL)
                tab.wait_for("document.querySelector('#nmt-state').textContent === 'PRE-OPERATIONAL'")
                assert tab.text("#cia402-state") == "SWITCH ON DISABLED"
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


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (Debian: apt-get install chromium; .ci/run "
                    "installs it)")
def test_page_of_a_force_actuator_shows_force_in_newtons(tmp_path):
    """An axis driven by a force actuator (a linear motor) reports its force in 0x6077: the page labels that
    channel force [N] (its recordings name it force_drive), not torque [N m]."""
    with served("--axis", "L=1:configs/examples/rigid-force-axis.toml", "--http", "127.0.0.1:0") as s:
        with Browser.launch(tmp_path) as browser:
            tab = browser.open(page_url(s))
            tab.wait_for("window.livePage && window.livePage.charts.length === 3")
            labels = tab.evaluate("window.livePage.charts[2].series.map((x) => x.label)")
            trig = tab.evaluate("[...document.querySelectorAll('#trig-chan option')].map((o) => o.textContent)")
    assert "force [N]" in labels and not any("torque" in x for x in labels), labels
    assert "force [N]" in trig, trig


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
    st, body = request(href, timeout_s=120.0)  # (the trace formatter compiles on its first use: slow on a busy host)
    assert st == 200, body  # (what the link downloads)
    tab.click("#rec-download")
    path = wait_for_file(downloads, ".csv", timeout_s=120)  # (the trace formatter compiles on its first use)
    from virtualaxis.diagnosis.trace import read_trace

    diag = subprocess.run([*CLI, "diagnose", "--config", CONFIG, str(path), "--out", str(downloads / "report"),
                           "--effects", "coulomb_friction", "--no-hybrid", "--jobs", "1"],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert diag.returncode == 0, diag.stderr
    report = json.loads((downloads / "report" / "report.json").read_text())
    # every row one instant, as `simulate` writes traces: diagnose needs to shift no channel
    assert not [f["note"] for f in report.get("alignment", []) if f["kind"] == "channel_shift"]
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
                st, body = raw_request(url, with_host(url, raw))
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


def _ws_frame(opcode: int, payload: bytes, *, masked: bool = True, rsv: int = 0, length: int | None = None,
              fin: bool = True) -> bytes:
    n = len(payload) if length is None else length
    head = bytes(((0x80 if fin else 0) | rsv | opcode,)) + (
        bytes(((0x80 if masked else 0) | n,)) if n < 126 else
        bytes(((0x80 if masked else 0) | 126,)) + n.to_bytes(2, "big") if n < 1 << 16 else
        bytes(((0x80 if masked else 0) | 127,)) + n.to_bytes(8, "big"))
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
            st, body = raw_request(url, with_host(url, raw.encode()))
            assert st == 400 and body["error"], raw
        st, body = request(url + f"api/axes/{AXIS}/objects")
        assert st == 200
        assert {(o["index"], o["sub"]): o.get("value") for o in body["objects"]}[("0x6081", 0)] != 1
        s.stop()
        assert "Traceback" not in s.stderr


def test_at_real_time_priority_the_state_messages_are_made_in_the_runtime_threads_gap(tmp_path):
    """serve --rt-priority: the page's state messages are made by the runtime thread in the gap before a drive
    cycle (serve's JSON counts them as gap jobs), not by a thread that would hold the interpreter lock while the
    drive's thread waits; they come ten times a second (fewer on a busy host), each with the drive's time
    advanced."""
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
        t_end = time.monotonic() + 60.0  # (until 10 new ones came: 1 s on an idle host; on a busy one the page's
        # server, at nice 10, gets little CPU: seen 3.5 per second beside four CPU-bound processes, fewer beside more)
        while time.monotonic() < t_end and len({c for c in cycles if c > 0}) < 10:
            op, data = _ws_read(sock)
            msg = json.loads(data)
            if op == 0x1 and msg["event"] == "state":
                cycles.append(msg["data"]["cycles"])
        sock.close()
    finally:
        cm.__exit__(None, None, None)
    # (the page's server sends the newest state at its own pace: one serve has not replaced yet comes twice)
    assert all(b >= a for a, b in zip(cycles, cycles[1:], strict=False)), cycles
    assert len({c for c in cycles if c > 0}) >= 10, cycles  # (10 new ones per second on an idle host)
    runtime = json.loads(out.read_text())["runtime"]
    # (a state sent twice was made once; cycles 0 is the zeroed block before any state, and the service makes
    # one itself as it starts)
    made = {c for c in cycles if c > 0}
    assert runtime["gap_jobs"] >= len(made) - 1 and runtime["gap_job_errors"] == 0, (runtime, cycles)


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


def _get(url: str, target: str, extra: str = "") -> tuple[int, dict]:
    """A GET of ``target`` (sent as it is, percent-escapes and all) with the Host of ``url``."""
    return raw_request(url, f"GET {target} HTTP/1.1\r\nHost: {urllib.parse.urlsplit(url).netloc}\r\n{extra}"
                            "\r\n".encode())


WS_HEADERS = "Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n" \
             "Sec-WebSocket-Version: 13\r\n"


def test_percent_escapes_that_are_not_utf8_are_refused_with_400():
    """A path whose percent-escapes decode to bytes that are not UTF-8 is a malformed request (400, JSON), on
    every route, not an internal error; a path is decoded once (an escaped % stays a %)."""
    with served("--http", "127.0.0.1:0", "--http-writable") as s:
        url = page_url(s)
        for target, extra in [("/%ff", ""), ("/api/axes/%ff%fe/objects", ""), ("/static/%ff", ""),
                              ("/api/axes/%ff/live", WS_HEADERS), ("/api/axes/%ff/events", ""),
                              (f"/api/axes/{AXIS}/%c3", ""), ("/%ed%a0%80", "")]:  # (the last: a surrogate)
            st, body = _get(url, target, extra)
            assert st == 400 and "percent-escape" in body["error"], (target, st, body)
        st, body = post(url, "/api/axes/%ff/write", b'{"index": "0x6081", "value": 1}')
        assert st == 400 and "percent-escape" in body["error"], body
        st, body = _get(url, f"/api/axes/{AXIS.replace('-', '%2D')}/objects")  # (valid escapes: as before)
        assert st == 200 and body["axis"] == AXIS
        st, body = _get(url, f"/api/axes/{AXIS.replace('-', '%252D')}/objects")  # %25 is "%": no axis of that name
        assert st == 404 and "seed000%2Dhust" in body["error"], body
        st, _, body = raw_exchange(url, f"GET /static/%61pp.js HTTP/1.1\r\nHost: {urllib.parse.urlsplit(url).netloc}"
                                        "\r\n\r\n".encode())
        assert st == 200 and body.startswith(b"// virtualaxis live drive page")
        s.stop()
        assert "Traceback" not in s.stderr, s.stderr


def test_write_and_fault_bodies_are_checked_for_their_shape_before_serve_gets_them():
    """A body nested deeper than a few levels is refused (400) before it is parsed further or forwarded to serve;
    a value that is not a number (or a string, for the string objects) is refused as an SDO would refuse it (422,
    abort code 0x06090030); a fault command's fields must be scalars of their types. serve logs no error."""
    with served("--http", "127.0.0.1:0", "--http-writable", "--allow-fault-injection") as s:
        url = page_url(s)
        api = f"/api/axes/{AXIS}"
        deep = b'{"index":"0x6081","sub":0,"value":' + b"[" * 500 + b"]" * 500 + b"}"
        st, body = post(url, api + "/write", deep)
        assert st == 400 and "deeper" in body["error"], (st, body)
        st, body = post(url, api + "/write", b'{"index":"0x6081","sub":0,"value":' + b"{\"a\":" * 300 + b"1" +
                        b"}" * 300 + b"}")
        assert st == 400 and "deeper" in body["error"], (st, body)
        for value in (b"[1]", b'{"v": 1}', b"null", b"true", b"[[[1]]]"):
            st, body = post(url, api + "/write", b'{"index": "0x6081", "sub": 0, "value": ' + value + b"}")
            assert st == 422 and body["abort_code"] == "0x06090030" and "must be a number" in body["error"], (
                value, st, body)
        st, body = post(url, api + "/write", b'{"index": "0x6081", "sub": 0, "value": "[]"}')  # a string: serve's
        assert st == 422 and body["abort_code"] == "0x06090030", body
        for command in (b'{"action": "inject", "kind": ' + b"[" * 500 + b"]" * 500 + b"}",
                        b'{"action": "inject", "kind": ["over_current"]}',
                        b'{"action": ["inject"], "kind": "over_current"}',
                        b'{"action": "inject", "kind": "over_current", "duty": [0.5]}',
                        b'{"action": "inject", "kind": "over_current", "id": {"a": 1}}'):
            st, body = post(url, api + "/fault", command)
            assert st == 400 and body["error"], (command[:60], st, body)
        assert value_of(url, "0x6081") != 1
        st, body = post(url, api + "/fault", b'{"action": "clear"}')
        assert st == 200 and body["active"] == [], body  # (no fault was injected)
        s.stop()
        assert "Traceback" not in s.stderr and "RecursionError" not in s.stderr, s.stderr


def _ws_close_of(sock: socket.socket) -> tuple[int, bytes]:
    """(code, reason) of the close frame the server sends next (other frames skipped)."""
    while (got := _ws_read(sock))[0] != 0x8:
        pass
    return int.from_bytes(got[1][:2], "big"), got[1][2:]


def _ws_until_pong(sock: socket.socket, token: bytes) -> list[dict]:
    """Send a ping ``token``; the error messages the server sent before its pong."""
    sock.sendall(_ws_frame(0x9, token))
    errors = []
    while True:
        op, data = _ws_read(sock)
        if op == 0xA and data == token:
            return errors
        if op == 0xA:  # (the pong of an earlier ping)
            continue
        assert op == 0x1, (op, data)
        msg = json.loads(data)
        if msg["event"] == "error":
            errors.append(msg["data"])


def test_websocket_reassembles_fragmented_messages():
    """Fragments make one message (a control frame may come between them): one error message for it, with its
    whole size; a continuation with no message started and a new data frame inside a fragmented message close
    the socket with 1002, fragments that add up to more than 4 KiB with 1009."""
    with served("--http", "127.0.0.1:0") as s:
        url = page_url(s)
        path = f"/api/axes/{AXIS}/live"
        sock = _ws_open(url, path)
        sock.sendall(_ws_frame(0x1, b'{"a": ', fin=False) + _ws_frame(0x9, b"between") +
                     _ws_frame(0x0, b'"b", ', fin=False) + _ws_frame(0x0, b'"c": 1}'))
        errors = _ws_until_pong(sock, b"after")  # (the pong of "between" came first: skipped as not "after")
        assert len(errors) == 1 and errors[0]["received_bytes"] == len(b'{"a": "b", "c": 1}'), errors
        sock.sendall(_ws_frame(0x2, b"\x00" * 3000, fin=False) + _ws_frame(0x0, b"\x00" * 1096))  # 4096: at the limit
        errors = _ws_until_pong(sock, b"binary")
        assert [e["received_bytes"] for e in errors] == [4096], errors
        sock.close()
        for frames, code, why in [
                ([_ws_frame(0x0, b"x")], 1002, "continuation"),
                ([_ws_frame(0x1, b"{", fin=False), _ws_frame(0x1, b"}")], 1002, "fragmented message is open"),
                ([_ws_frame(0x1, b"{", fin=False), _ws_frame(0x2, b"}", fin=False)], 1002, "fragmented message"),
                ([_ws_frame(0x1, b"{", fin=False), _ws_frame(0x0, b"x" * 2000, fin=False),
                  _ws_frame(0x0, b"x" * 2000, fin=False), _ws_frame(0x0, b"x" * 2000)], 1009, "at most 4096"),
                ([_ws_frame(0x1, b"{}"), _ws_frame(0x0, b"x")], 1002, "continuation")]:
            sock = _ws_open(url, path)
            sock.sendall(b"".join(frames))
            got, reason = _ws_close_of(sock)
            assert got == code and why in reason.decode(), (frames[0][:2], got, reason)
            sock.close()
        s.stop()
        assert "Traceback" not in s.stderr, s.stderr


def test_websocket_close_frames_and_text_are_validated():
    """A close frame of 1 byte, with a code RFC 6455 7.4 does not allow on the wire or a reason that is not UTF-8
    is answered with close 1002; a valid close gets its code echoed. A text message that is not UTF-8 (also split
    across fragments) closes with 1007, a 64-bit length with its top bit set with 1002."""
    with served("--http", "127.0.0.1:0") as s:
        url = page_url(s)
        path = f"/api/axes/{AXIS}/live"

        def closed_with(frame: bytes) -> tuple[int, bytes]:
            sock = _ws_open(url, path)
            try:
                sock.sendall(frame)
                return _ws_close_of(sock)
            finally:
                sock.close()

        for code in (0, 999, 1004, 1005, 1006, 1015, 1016, 2000, 2999, 5000, 65535):
            got, reason = closed_with(_ws_frame(0x8, code.to_bytes(2, "big")))
            assert got == 1002 and b"close code" in reason, (code, got, reason)
        assert closed_with(_ws_frame(0x8, b"\x03"))[0] == 1002
        assert closed_with(_ws_frame(0x8, (1000).to_bytes(2, "big") + b"bye \xff"))[0] == 1002
        for code in (1000, 1001, 1003, 1011, 3000, 4999):
            assert closed_with(_ws_frame(0x8, code.to_bytes(2, "big") + "fin é".encode())) == (code, b""), code
        assert closed_with(_ws_frame(0x8, b"")) == (0, b"")  # (no code: none echoed; _ws_close_of reads 0)
        got, reason = closed_with(_ws_frame(0x1, b'{"a": "\xff\xfe"}'))
        assert got == 1007 and b"UTF-8" in reason, (got, reason)
        got, _ = closed_with(_ws_frame(0x1, b'{"a": "\xc3', fin=False) + _ws_frame(0x0, b'("}'))  # (C3 28: invalid)
        assert got == 1007
        top = bytes((0x81, 0x80 | 127)) + ((1 << 63) | 5).to_bytes(8, "big") + b"\x01\x02\x03\x04" + b"x" * 5
        got, reason = closed_with(top)
        assert got == 1002 and b"most significant bit" in reason, (got, reason)
        # valid: UTF-8 split across fragments (é = C3 A9) is one text message, answered with an error message
        sock = _ws_open(url, path)
        sock.sendall(_ws_frame(0x1, b'{"a": "\xc3', fin=False) + _ws_frame(0x0, b'\xa9"}'))
        assert len(_ws_until_pong(sock, b"ok")) == 1
        sock.close()
        s.stop()
        assert "Traceback" not in s.stderr, s.stderr


def test_duplicate_headers_that_must_be_single_are_refused():
    """Two Content-Length headers (conflicting or not), two Content-Type, two Host, or a handshake with two
    Sec-WebSocket-Key are refused with 400 (RFC 9112 6.3, 3.2; RFC 6455 4.2.1): nothing is written."""
    with served("--http", "127.0.0.1:0", "--http-writable") as s:
        url = page_url(s)
        path = f"/api/axes/{AXIS}/write"
        body = b'{"index": "0x6081", "sub": 0, "value": 4242}'
        for headers in [f"Content-Length: 5\r\nContent-Length: {len(body)}\r\n",
                        f"Content-Length: {len(body)}\r\nContent-Length: 5\r\n",
                        f"Content-Length: {len(body)}\r\nContent-Length: {len(body)}\r\n",
                        f"Content-Length: {len(body)}, {len(body)}\r\n"]:
            st, answer = raw_request(url, with_host(url, f"POST {path} HTTP/1.1\r\nContent-Type: application/json"
                                                         f"\r\n{headers}\r\n".encode() + body))
            assert st == 400 and "Content-Length" in answer["error"], (headers, st, answer)
        st, answer = post(url, path, body, "Content-Type: application/json\r\nContent-Type: text/plain\r\n")
        assert st == 400 and "Content-Type" in answer["error"], answer
        st, answer = post(url, path, body, "Content-Type: application/json\r\nHost: 127.0.0.1\r\n")
        assert st == 400 and "Host" in answer["error"], answer
        assert value_of(url, "0x6081") != 4242
        st, answer = _get(url, f"/api/axes/{AXIS}/live", WS_HEADERS + "Sec-WebSocket-Key: AAAAAAAAAAAAAAAAAAAAAA==\r\n")
        assert st == 400 and "Sec-WebSocket-Key" in answer["error"], answer
        st, answer = post(url, path, body)  # (the same write, once each header: applied)
        assert st == 200 and value_of(url, "0x6081") == 4242


def test_cross_site_requests_cannot_write_inject_or_open_the_socket():
    """What a web page of another site could send from a browser on the drive's host is refused: a POST without
    Content-Type: application/json (415), a POST or a WebSocket handshake with another Origin (403), a request
    whose Host is not loopback on a loopback server (DNS rebinding, 403). The page's own origin passes."""
    with served("--http", "127.0.0.1:0", "--http-writable", "--allow-fault-injection") as s:
        url = page_url(s)
        host = urllib.parse.urlsplit(url).netloc
        port = urllib.parse.urlsplit(url).port
        write, fault = f"/api/axes/{AXIS}/write", f"/api/axes/{AXIS}/fault"
        body = b'{"index": "0x6081", "sub": 0, "value": 777}'
        inject = b'{"action": "inject", "kind": "over_current"}'
        for path, data in ((write, body), (fault, inject)):
            st, answer = post(url, path, data, "")
            assert st == 415 and "Content-Type" in answer["error"], (path, st, answer)
            st, answer = post(url, path, data, "Content-Type: text/plain;charset=UTF-8\r\n")
            assert st == 415, (path, st, answer)
            for origin in ("http://evil.example", "null", f"http://127.0.0.1:{port + 1}", f"https://{host}",
                           f"http://localhost:{port}", "http://127.0.0.1"):
                st, answer = post(url, path, data, f"Content-Type: application/json\r\nOrigin: {origin}\r\n")
                assert st == 403 and "Origin" in answer["error"], (path, origin, st, answer)
            st, answer = raw_request(url, f"POST {path} HTTP/1.1\r\nHost: evil.example:{port}\r\nOrigin: "
                                          f"http://evil.example:{port}\r\nContent-Type: application/json\r\n"
                                          f"Content-Length: {len(data)}\r\n\r\n".encode() + data)
            assert st == 403 and "loopback" in answer["error"], (path, st, answer)
        st, answer = raw_request(url, f"POST {write} HTTP/1.1\r\nContent-Type: application/json\r\n"
                                      f"Content-Length: {len(body)}\r\n\r\n".encode() + body)
        assert st == 400 and "Host" in answer["error"], answer
        assert value_of(url, "0x6081") != 777
        for origin in ("http://evil.example", "null"):
            st, answer = _get(url, f"/api/axes/{AXIS}/live", WS_HEADERS + f"Origin: {origin}\r\n")
            assert st == 403 and "Origin" in answer["error"], (origin, st, answer)
        st, answer = raw_request(url, f"GET /api/axes HTTP/1.1\r\nHost: attacker.example:{port}\r\n\r\n".encode())
        assert st == 403, answer
        # the page's own origin: written, injected, the socket opens
        st, answer = post(url, write, body, f"Content-Type: application/json; charset=utf-8\r\nOrigin: http://{host}\r\n")
        assert st == 200 and answer["value"] == 777, answer
        st, answer = post(url, fault, b'{"action": "clear"}', f"Content-Type: application/json\r\nOrigin: http://{host}\r\n")
        assert st == 200 and answer["active"] == [], answer  # (none of the refused injections was applied)
        sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        sock.sendall(f"GET /api/axes/{AXIS}/live HTTP/1.1\r\nHost: localhost:{port}\r\nOrigin: http://localhost:"
                     f"{port}\r\n{WS_HEADERS}\r\n".encode())
        assert sock.recv(12) == b"HTTP/1.1 101"
        sock.close()


def test_fault_injection_through_the_page_needs_http_writable_and_allow_fault_injection():
    """The page's fault endpoint (and its buttons, shown from /api/axes' fault_injection) needs both flags: with
    one of them the command is refused with 403 naming the other, and /api/axes says no."""
    inject = b'{"action": "inject", "kind": "over_current"}'
    for flags, missing in [(("--allow-fault-injection",), "--http-writable"),
                           (("--http-writable",), "--allow-fault-injection"), ((), "--http-writable and "
                                                                                 "--allow-fault-injection")]:
        with served("--http", "127.0.0.1:0", *flags) as s:
            url = page_url(s)
            st, body = post(url, f"/api/axes/{AXIS}/fault", inject)
            assert st == 403 and body["error"].endswith(f"(missing: {missing})"), (flags, st, body)
            assert body["abort_code"] == "0x08000022"
            st, info = request(url + "api/axes")
            assert info["axes"][0]["fault_injection"] is False, (flags, info)
            assert info["writable"] is ("--http-writable" in flags)
    with served("--http", "127.0.0.1:0", "--http-writable", "--allow-fault-injection") as s:
        url = page_url(s)
        st, info = request(url + "api/axes")
        assert info["writable"] is True and info["axes"][0]["fault_injection"] is True
        st, body = post(url, f"/api/axes/{AXIS}/fault", inject)
        assert st == 200 and body["ok"] is True and "over_current" in body["active"], body


def test_concurrent_recording_downloads_are_capped():
    """At most 4 recordings are built and sent at once (each holds its samples and CSV text in memory): the
    requests beyond get 503 with Retry-After and a JSON error, and once the downloads are done a recording is
    served again."""
    with served("--http", "127.0.0.1:0") as s:
        url = page_url(s)
        u = urllib.parse.urlsplit(url)
        target = f"/api/axes/{AXIS}/recording.csv?from=0&to=3000"
        deadline = time.monotonic() + 30
        while (st := request(url + target[1:], timeout_s=120)[0]) != 200 and time.monotonic() < deadline:
            time.sleep(0.2)  # (the samples of the first 3 s; the first recording loads the trace writer: on a busy
            # host the page's server, at nice 10, may take a minute for it)
        assert st == 200
        raw = f"GET {target} HTTP/1.1\r\nHost: {u.netloc}\r\n\r\n".encode()
        socks = [socket.create_connection((u.hostname, u.port), timeout=30) for _ in range(24)]
        for sock in socks:  # all requests sent before any answer is read
            sock.sendall(raw)
        answers = []
        for sock in socks:
            data = b""
            while chunk := sock.recv(1 << 16):
                data += chunk
            sock.close()
            head, _, body = data.partition(b"\r\n\r\n")
            answers.append((int(head.split(b" ")[1]), head.decode("latin-1"), body))
        busy = [a for a in answers if a[0] == 503]
        assert busy and all(a[0] in (200, 503) for a in answers), [a[0] for a in answers]
        for _, head, body in busy:
            assert "\r\nRetry-After: 1" in head and "recordings" in json.loads(body)["error"]
        for status, _, body in answers:
            if status == 200:
                assert len(body.splitlines()) == 3001  # (header and every sample)
        st, csv = request(url + target[1:])
        assert st == 200 and len(csv.strip().splitlines()) == 3001


def test_a_real32_write_beyond_its_range_is_refused_as_value_too_high_or_low():
    """A number beyond REAL32 (1e39) or a float (1e400) written to a REAL32 object is refused as SDO refuses an
    out-of-range value: abort 0x06090031 (too high) / 0x06090032 (too low), the text naming the object and its
    range."""
    with served("--http", "127.0.0.1:0", "--http-writable") as s:
        url = page_url(s)
        path = f"/api/axes/{AXIS}/write"
        before = value_of(url, "0x2000")
        for index, value, code, words in [
                ("0x2000", b"1e39", "0x06090031", ("Position loop gain Kv", "1e+39 is above its range 0 .. 2000")),
                ("0x2000", b"1e400", "0x06090031", ("Position loop gain Kv", "above its range 0 .. 2000")),
                ("0x2000", b"2500", "0x06090031", ("Position loop gain Kv", "2500 is above its range 0 .. 2000")),
                ("0x2011", b"-1e39", "0x06090032", ("External force", "-1e+39 is below its range -1000000 .. 1000000")),
                ("0x6081", b"1e39", "0x06090031", ("above its range 0 .. 4294967295",))]:
            st, body = post(url, path, b'{"index": "' + index.encode() + b'", "sub": 0, "value": ' + value + b"}")
            assert st == 422 and body["abort_code"] == code, (index, value, st, body)
            assert body["error"].startswith(f"{index}:0: ") and all(w in body["error"] for w in words), body
        assert value_of(url, "0x2000") == before


def test_numbers_are_plain_ascii_and_integers_are_json_integers():
    """An index or sub-index is a JSON integer or ASCII decimal digits or 0x and hex digits; a recording's bounds
    are ASCII digits; a fault kind is a name or an integral number: signs, blanks, underscores, other scripts'
    digits and fractions are refused with 400 naming the field."""
    with served("--http", "127.0.0.1:0", "--http-writable", "--allow-fault-injection") as s:
        url = page_url(s)
        path = f"/api/axes/{AXIS}/write"
        for field, text in [("index", '"0x60_81"'), ("index", '"+0x6081"'), ("index", '" 0x6081 "'),
                            ("index", '"0x\u0666\u0660\u0668\u0661"'), ("index", '"\u0662\u0664\u0667\u0660\u0665"'),
                            ("index", '"24_705"'), ("index", '"-0"'), ("index", "24705.0"), ("index", '"0x"'),
                            ("index", '"0b101"'), ("index", '"0o60201"'), ("index", '"２４７０５"'),
                            ("sub", '"+0"'), ("sub", "0.0"), ("sub", '" 0"'), ("sub", '"\u0660"')]:
            doc = {"index": '"0x6081"', "sub": "0", field: text}
            body = '{"index": ' + doc["index"] + ', "sub": ' + doc["sub"] + ', "value": 5150}'
            st, answer = post(url, path, body.encode())
            assert st == 400 and answer["error"].startswith(f"{field}:"), (field, text, st, answer)
        assert value_of(url, "0x6081") != 5150
        for index in ('"0x6081"', '"0X6081"', '"24705"', "24705"):
            st, answer = post(url, path, b'{"index": %s, "sub": "0", "value": 5150}' % index.encode())
            assert st == 200 and answer["value"] == 5150, (index, answer)
        for field, query in [("from", "from=\u0661&to=2"), ("to", "from=0&to=\u0662"), ("from", "from=%2B1&to=2"),
                             ("from", "from=%201&to=2"), ("from", "from=1.0&to=2"), ("to", "from=0&to=0x10")]:
            st, answer = _get(url, f"/api/axes/{AXIS}/recording.csv?{urllib.parse.quote(query, safe='=&%')}")
            assert st == 400 and answer["error"].startswith(f"{field}:"), (query, st, answer)
        for kind in ("4.5", "true", '["4"]', '{"n": 4}'):
            st, answer = post(url, f"/api/axes/{AXIS}/fault", b'{"action": "inject", "kind": %s}' % kind.encode())
            assert st == 400 and answer["error"].startswith("kind:"), (kind, st, answer)
        for kind in ("4", "4.0"):  # (an integral number, as MQTT's fault/set takes it: judged by the drive)
            st, answer = post(url, f"/api/axes/{AXIS}/fault", b'{"action": "clear"}')
            assert st == 200 and answer["active"] == [], answer
            st, answer = post(url, f"/api/axes/{AXIS}/fault", b'{"action": "inject", "kind": %s}' % kind.encode())
            assert st in (200, 422) and "kind" not in answer.get("error", "")[:5], (kind, answer)


def test_expect_100_continue_gets_its_interim_answer_before_the_body_is_sent():
    """RFC 9110 10.1.1: a client that sends ``Expect: 100-continue`` waits for ``100 Continue`` before it sends
    the body (curl does so for bodies over 1 KiB); the server sends it and then the final answer. Any other
    expectation is refused with 417 and nothing is written."""
    with served("--http", "127.0.0.1:0", "--http-writable") as s:
        url = page_url(s)
        u = urllib.parse.urlsplit(url)
        body = b'{"index": "0x6081", "sub": 0, "value": 4321}'
        with socket.create_connection((u.hostname, u.port), timeout=20) as sock:
            sock.sendall(f"POST /api/axes/{AXIS}/write HTTP/1.1\r\nHost: {u.netloc}\r\nContent-Type: "
                         f"application/json\r\nExpect: 100-continue\r\nContent-Length: {len(body)}\r\n\r\n"
                         .encode())
            interim = b""
            while not interim.endswith(b"\r\n\r\n"):  # (before the body: the old server sent nothing here)
                chunk = sock.recv(1)
                assert chunk, interim
                interim += chunk
            assert interim == b"HTTP/1.1 100 Continue\r\n\r\n"
            sock.sendall(body)
            data = b""
            while chunk := sock.recv(65536):
                data += chunk
        assert data.startswith(b"HTTP/1.1 200 "), data[:200]
        assert value_of(url, "0x6081") == 4321
        st, answer = post(url, f"/api/axes/{AXIS}/write", b'{"index": "0x6081", "sub": 0, "value": 1234}',
                          "Content-Type: application/json\r\nExpect: something-else\r\n")
        assert st == 417 and "100-continue" in answer["error"], answer
        assert value_of(url, "0x6081") == 4321


def test_not_found_answers_name_what_exists():
    """A 404 says what the client probably meant: the axis list without its trailing slash, an axis's resources,
    a path with an empty first segment."""
    with served("--http", "127.0.0.1:0") as s:
        url = page_url(s)
        st, body = _get(url, "/api/axes/")
        assert st == 404 and "/api/axes (no trailing slash)" in body["error"], body
        st, body = _get(url, f"/api/axes/{AXIS}/")
        assert st == 404 and "recording.csv" in body["error"] and "objects" in body["error"], body
        st, body = _get(url, f"/api/axes/{AXIS}/nothing")
        assert st == 404 and "'nothing'" in body["error"] and "events" in body["error"], body
        st, body = _get(url, "//api/axes")
        assert st == 404 and "empty segment" in body["error"], body
        st, objs = request(url + f"api/axes/{AXIS}/objects")
        wo = [o for o in objs["objects"] if o["access"] == "wo"]
        assert wo and all("value" not in o and "read_abort" not in o for o in wo), wo


def test_refusals_beyond_4xx_are_answered_and_documented():
    """The server answers 505 to an HTTP version it does not speak, 501 to Transfer-Encoding and 503 to a stream
    or recording beyond its limits; docs/live-page.md says so beside its 4xx refusals."""
    with served("--http", "127.0.0.1:0", "--http-writable") as s:
        url = page_url(s)
        st, body = raw_request(url, b"GET /api/axes HTTP/2.0\r\n\r\n")
        assert st == 505 and body["error"]
        st, body = raw_request(url, with_host(url, f"POST /api/axes/{AXIS}/write HTTP/1.1\r\nTransfer-Encoding: "
                                                   "chunked\r\nContent-Type: application/json\r\n\r\n".encode()))
        assert st == 501 and body["error"]
    doc = (Path(ROOT) / "docs" / "live-page.md").read_text()
    refusals = doc[doc.index("Every refusal"):].split("\n\n")[0]
    for code in ("4xx", "501", "503", "505"):
        assert code in refusals, (code, refusals)
    assert "Retry-After" in doc and "Origin" in doc and "415" in doc


def _stream(url: str, seconds: float, out: dict, min_states: int = 0) -> None:
    """Read one event stream for ``seconds``, and on until ``min_states`` state messages came (at most 60 s: a busy
    host gives the page's server, at nice 10, little CPU): scope sequence numbers and state messages."""
    u = urllib.parse.urlsplit(url)
    conn = http.client.HTTPConnection(u.hostname, u.port, timeout=10)
    conn.request("GET", u.path)
    r = conn.getresponse()
    out["status"] = r.status
    end, last = time.monotonic() + seconds, time.monotonic() + 60.0
    event = None
    while (now := time.monotonic()) < end or (out.get("states", 0) < min_states and now < last):
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


def _live(url: str, axis: str, seconds: float, out: dict, min_states: int = 0) -> None:
    """Read one axis's WebSocket for ``seconds`` as the page does, and on until ``min_states`` state messages came
    (at most 60 s): scope sequence numbers (each message's samples decoded) and state messages."""
    import base64

    sock = _ws_open(url, f"/api/axes/{axis}/live")
    end, last = time.monotonic() + seconds, time.monotonic() + 60.0
    try:
        while (now := time.monotonic()) < end or (out.get("states", 0) < min_states and now < last):
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
        threads = [threading.Thread(target=_live, args=(url, "XYZ"[i % 3], 3.0, outs[i], 10)) if i % 5 else
                   threading.Thread(target=_stream, args=(f"{url}api/axes/{'XYZ'[i % 3]}/events", 3.0, outs[i], 10))
                   for i in range(10)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(90)
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


def test_a_ring_row_holds_one_instant_of_the_drive():
    """A hook's slot holds the position loop's sample of its cycle (0x6062, 0x6064, 0x60F4: taken at the cycle's
    start) with the velocity, torque and current at the cycle's end; a row of the long ring pairs the sample with
    the values at the same instant (those of the slot before), as `simulate` writes its traces. The first row
    after a loss keeps its own."""
    from types import SimpleNamespace

    from virtualaxis.services.http.ring import HANDOFF_MARGIN, HANDOFF_SLOTS, LongRing, PageBlock, segment_size

    buf = memoryview(bytearray(segment_size(1)))
    block = PageBlock(buf, 0)
    drive = SimpleNamespace(outputs=(None,) * 15, objects={(0x6041, 0): 0x637},
                            scaling=SimpleNamespace(metres_per_unit=1e-6), read_object=lambda index: 1000)
    block.set_units(drive)
    ring = LongRing(block, 1e-3, seconds=60.0)

    def cycles(first: int, n: int) -> None:
        for k in range(first, first + n):  # position k, velocity 10 k, torque 2 k, current 3 k per mille
            drive.outputs = (8, k, 0, k, 0, 10 * k, 2 * k, 3 * k, 0, 0, 0, 25.0, 0, k, 0)
            block.hook(drive)

    cycles(0, 50)
    ring.drain()
    cycles(50, 50)  # (a second drain: the slot before its first is the last of the first drain)
    ring.drain()
    _, rows = ring.slice(0, 100)
    k = np.arange(100)
    assert np.allclose(rows[:, 1], 1e-6 * k)  # pos_fb of slot k
    assert np.allclose(rows[1:, 3], 10e-6 * (k[1:] - 1)) and rows[0, 3] == 0.0  # velocity of slot k - 1
    assert np.allclose(rows[1:, 4], 2e-3 * (k[1:] - 1)) and np.allclose(rows[1:, 5], 3e-3 * (k[1:] - 1))
    cycles(100, HANDOFF_SLOTS + 10)  # the server away too long: slots lost
    first, end = ring.drain()
    assert ring.lost == HANDOFF_SLOTS + 10 - (HANDOFF_SLOTS - HANDOFF_MARGIN)
    _, rows = ring.slice(first, end)
    k0 = 100 + ring.lost
    assert rows[0, 3] == pytest.approx(10e-6 * k0) and rows[1, 3] == pytest.approx(10e-6 * k0)


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
