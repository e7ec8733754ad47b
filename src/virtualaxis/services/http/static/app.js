// virtualaxis live drive page: state, scope, parameters of one served axis (docs/live-page.md).
"use strict";

const SW_BITS = ["ready to switch on", "switched on", "operation enabled", "fault", "voltage enabled",
  "quick stop (0 = active)", "switch on disabled", "warning", "manufacturer 8", "remote", "target reached",
  "internal limit active", "op-mode specific 12 (set-point ack / speed zero / homing attained)",
  "op-mode specific 13 (following error / homing error)", "manufacturer 14", "manufacturer 15"];
// column of a ring row -> [label, scale to the shown unit, unit]
const CHANNELS = {
  pos_cmd: ["position demand", 1e3, "mm"], pos_fb: ["position actual", 1e3, "mm"],
  following_error: ["following error", 1e6, "um"], vel_meas: ["speed", 1e3, "mm/s"],
  torque_meas: ["torque", 1, "N m"], current_q: ["current", 1, "A"], statusword: ["statusword", 1, ""],
};
const KEEP_S = 60;  // seconds of samples kept in the page (the server's ring keeps more: recordings come from there)

const page = {  // (also read by the browser tests)
  info: null, axis: null, cols: [], chunks: [], kept: 0, lastSeq: -1, samplesReceived: 0, gaps: 0,
  paused: false, zoomed: false, dirty: false, charts: [], trigger: {mode: "none", armed: false, at: null},
  rec: {from: null, to: null}, cursors: [], cursorReadout: null, stateMessages: 0, lastState: null, view: null,
  fullView: null,
};
window.livePage = page;

const $ = (id) => document.getElementById(id);
const esc = (s) => String(s).replace(/[&<>"']/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}[c]));
const api = (path) => "/api/axes/" + encodeURIComponent(page.axis.name) + path;

async function main() {
  page.info = await (await fetch("/api/axes")).json();
  page.cols = page.info.columns;
  const wanted = new URLSearchParams(location.search).get("axis");
  page.axis = page.info.axes.find((a) => a.name === wanted) || page.info.axes[0];
  if (page.axis.force_actuator) CHANNELS.torque_meas = ["force", 1, "N"];  // (0x6077 of a force actuator: its force)
  $("axis-title").textContent = `${page.axis.name} (node ${page.axis.node_id})`;
  document.title = `${page.axis.name} - virtualaxis`;
  $("axis-tabs").innerHTML = page.info.axes.map((a) =>
    `<a href="?axis=${encodeURIComponent(a.name)}" class="${a.name === page.axis.name ? "current" : ""}">${esc(a.name)}</a>`).join("");
  setupScope();
  setupInjection();
  setupParams();
  connect();
  requestAnimationFrame(frame);
}

// ------------------------------------------------------------------------------------------------ events
// a WebSocket (not server-sent events: a browser opens at most 6 HTTP/1.1 streams per server, 10 tabs would stall)
function connect() {
  const ws = new WebSocket((location.protocol === "https:" ? "wss://" : "ws://") + location.host + api("/live"));
  page.socket = ws;
  ws.onopen = () => { $("link-status").textContent = "live"; $("link-status").className = "badge live"; };
  ws.onclose = () => {
    $("link-status").textContent = "reconnecting"; $("link-status").className = "badge down";
    setTimeout(connect, 1000);
  };
  ws.onmessage = (ev) => {
    const m = JSON.parse(ev.data);
    if (m.event === "scope") addChunk(m.data);
    else if (m.event === "state") showState(m.data);
  };
}

function addChunk(m) {
  const bin = atob(m.b64);
  const bytes = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
  const data = new Float32Array(bytes.buffer);
  if (page.lastSeq >= 0 && m.seq0 !== page.lastSeq + 1) page.gaps++;
  const chunk = {seq0: m.seq0, t0: m.t0, dt: m.dt, n: m.n, cols: m.cols, data};
  page.chunks.push(chunk);
  page.kept += m.n;
  page.lastSeq = m.seq0 + m.n - 1;
  page.samplesReceived += m.n;
  const maxKeep = Math.ceil(KEEP_S / m.dt);
  while (page.kept - page.chunks[0].n > maxKeep) page.kept -= page.chunks.shift().n;
  checkTrigger(chunk);
  page.dirty = true;
}

// ------------------------------------------------------------------------------------------------ state
function showState(s) {
  page.lastState = s;
  page.stateMessages++;
  const st = $("cia402-state");
  st.textContent = s.cia402_state;
  st.className = "state-" + s.cia402_state;
  $("nmt-state").textContent = s.nmt_state ?? "-";
  $("mode").textContent = `${s.mode} (${s.mode_name})`;
  $("statusword").textContent = "0x" + s.statusword.toString(16).toUpperCase().padStart(4, "0");
  $("controlword").textContent = "0x" + s.controlword.toString(16).toUpperCase().padStart(4, "0");
  $("positions").textContent = `${(s.position_actual_m * 1e3).toFixed(4)} mm / ${(s.position_demand_m * 1e3).toFixed(4)} mm`;
  $("following-error").textContent = `${(s.following_error_m * 1e6).toFixed(2)} um`;
  $("error-code").textContent = s.error_code;
  const dc = s.drive_counters || {};
  $("overruns").textContent = `${dc.overruns ?? "-"} of ${dc.cycles ?? "-"} drive cycles`;
  $("bus-load").textContent = s.bus ? `${s.bus.load_percent.toFixed(1)} % (peak ${s.bus.peak_load_percent.toFixed(1)} %) of ${s.bus.bitrate_bit_s} bit/s` : "not emulated (--bitrate 0)";
  $("ring-info").textContent = `${s.ring.written} / ${s.ring.lost} (server keeps ${s.ring.capacity_s.toFixed(0)} s)`;
  $("sw-bits").innerHTML = SW_BITS.map((name, b) =>
    `<li class="${s.statusword_bits[b] ? "on" : "off"}" data-bit="${b}">${b}: ${esc(name)}</li>`).join("");
  $("faults").tBodies[0].innerHTML = s.faults.map((f) => `<tr><td>${f.emcy_code}</td><td>${f.fault_number}</td>` +
    `<td>${esc(f.text)}</td><td>${f.value}</td><td>${f.time_s.toFixed(3)}</td>` +
    `<td>${f.acknowledged ? "acknowledged" : "active"}${f.injected ? ", injected" : ""}</td></tr>`).join("");
  $("warnings").tBodies[0].innerHTML = s.warnings.map((w) =>
    `<tr><td>${w.emcy_code}</td><td>${w.alarm_number}</td><td>${esc(w.text)}</td></tr>`).join("");
  $("bus-events").tBodies[0].innerHTML = s.bus_events.map((e) => `<tr><td>${e.age_s.toFixed(1)}</td><td>${e.kind}</td>` +
    `<td>${e.emcy_code || e.abort_code || ""}</td><td>${esc(e.text || e.object || "")}</td><td>${e.data}</td></tr>`).join("");
}

// ------------------------------------------------------------------------------------------------ scope
function setupScope() {
  const sync = uPlot.sync("scope");
  const width = Math.max(400, $("charts").clientWidth - 10);
  const mk = (title, series, scales) => {
    const opts = {
      title, width, height: 190,
      cursor: {sync: {key: sync.key}, drag: {x: true, y: false, setScale: false}},
      scales: {x: {time: false}, ...scales},
      axes: [{label: "t [s]"}, ...series.filter((s) => s.axis).map((s) => s.axis)],
      series: [{label: "t [s]"}, ...series.map((s) => s.series)],
      hooks: {setSelect: [zoomToSelection], draw: [drawCursors]},
    };
    const u = new uPlot(opts, [[], ...series.map(() => [])], $("charts"));
    u.over.addEventListener("click", () => setCursor(u));
    u.over.addEventListener("dblclick", () => unzoom());
    return u;
  };
  const ser = (col, stroke, scale) => ({col, series: {label: `${CHANNELS[col][0]} [${CHANNELS[col][2]}]`, stroke, scale, width: 1.5}});
  page.charts = [
    mk("Position", [ser("pos_cmd", "#1f5fd6", "mm"), {...ser("pos_fb", "#d6551f", "mm"), axis: {scale: "mm", label: "mm"}}], {}),
    mk("Following error", [{...ser("following_error", "#7a2fb8", "um"), axis: {scale: "um", label: "um"}}], {}),
    mk(`Speed, current, ${CHANNELS.torque_meas[0]}`, [{...ser("vel_meas", "#0a8", "v"), axis: {scale: "v", label: "mm/s"}},
      {...ser("current_q", "#c80", "a"), axis: {scale: "a", side: 1, label: `A / ${CHANNELS.torque_meas[2]}`,
        grid: {show: false}}},
      ser("torque_meas", "#888", "a")], {}),
  ];
  page.chartCols = [["pos_cmd", "pos_fb"], ["following_error"], ["vel_meas", "current_q", "torque_meas"]];
  $("pause").onclick = () => setPaused(!page.paused);
  $("unzoom").onclick = unzoom;
  $("span").onchange = () => { page.dirty = true; };
  const chan = $("trig-chan");
  chan.innerHTML = page.cols.filter((c) => c !== "statusword").map((c) =>
    `<option value="${c}">${CHANNELS[c][0]} [${CHANNELS[c][2]}]</option>`).join("");
  $("trig-mode").onchange = () => {
    const m = $("trig-mode").value;
    $("trig-bit-box").hidden = m !== "bit";
    $("trig-thr-box").hidden = m !== "threshold";
  };
  $("trig-arm").onclick = armTrigger;
  $("rec").onclick = toggleRecording;
  window.addEventListener("resize", () => {
    const w = Math.max(400, $("charts").clientWidth - 10);
    page.charts.forEach((u) => u.setSize({width: w, height: 190}));
  });
}

function setPaused(p) {
  page.paused = p;
  $("pause").textContent = p ? "Run" : "Pause";
  if (!p) { page.zoomed = false; page.trigger.at = null; page.dirty = true; }
}

function unzoom() {
  page.zoomed = false; page.dirty = true;
  if (!page.paused) draw(); else drawView(page.fullView, true);
}

// a dragged time range: every plot shows the samples of that window (the x axis spans its first to its last sample)
function zoomToSelection(u) {
  const sel = u.select;
  if (!(sel.width >= 3)) return;
  const a = seqAtTime(u.posToVal(sel.left, "x"), Math.ceil), b = seqAtTime(u.posToVal(sel.left + sel.width, "x"), Math.floor);
  u.setSelect({left: 0, top: 0, width: 0, height: 0}, false);
  if (a === null || b === null || b <= a) return;
  page.zoomed = true;
  drawView([a, b + 1], true);
}

function sampleAt(seq) {  // [chunk, index] of a sequence number, or null
  for (const c of page.chunks) if (seq >= c.seq0 && seq < c.seq0 + c.n) return [c, seq - c.seq0];
  return null;
}

// the sequence number of the sample at time t (round: the nearest one), clamped to the samples kept; null if none
function seqAtTime(t, round = Math.round) {
  if (!page.chunks.length) return null;
  const first = page.chunks[0], last = page.chunks[page.chunks.length - 1];
  if (t <= first.t0) return first.seq0;
  if (t >= last.t0 + (last.n - 1) * last.dt) return last.seq0 + last.n - 1;
  for (let i = page.chunks.length - 1; i >= 0; i--) {
    const c = page.chunks[i];
    if (t >= c.t0) return c.seq0 + Math.min(c.n - 1, round((t - c.t0) / c.dt));
  }
  return first.seq0;
}

function timeOf(seq) { const s = sampleAt(seq); return s ? s[0].t0 + s[1] * s[0].dt : null; }

// the samples of [seqFrom, seqTo) decimated to ~2 points per pixel (min and max of each bucket)
function decimated(seqFrom, seqTo, pixels) {
  const colIdx = page.chartCols.map((cs) => cs.map((c) => page.cols.indexOf(c)));
  const scale = page.chartCols.map((cs) => cs.map((c) => CHANNELS[c][1]));
  const n = Math.max(0, seqTo - seqFrom);
  const k = Math.max(1, Math.ceil(n / Math.max(1, pixels)));
  const xs = [], ys = page.chartCols.map((cs) => cs.map(() => []));
  let bucket = null;
  const flush = () => {
    if (!bucket) return;
    xs.push(bucket.t0, bucket.t1);
    bucket.lo.forEach((row, ci) => row.forEach((lo, si) => {
      const hi = bucket.hi[ci][si];
      ys[ci][si].push(bucket.first[ci][si] <= bucket.last[ci][si] ? lo : hi, bucket.first[ci][si] <= bucket.last[ci][si] ? hi : lo);
    }));
    bucket = null;
  };
  for (const c of page.chunks) {
    const a = Math.max(seqFrom, c.seq0), b = Math.min(seqTo, c.seq0 + c.n);
    for (let s = a; s < b; s++) {
      const i = s - c.seq0, t = c.t0 + i * c.dt, row = i * c.cols;
      if (!bucket || (s - seqFrom) % k === 0) {
        flush();
        bucket = {t0: t, t1: t, lo: colIdx.map((cs) => cs.map(() => Infinity)), hi: colIdx.map((cs) => cs.map(() => -Infinity)),
          first: colIdx.map((cs) => cs.map(() => 0)), last: colIdx.map((cs) => cs.map(() => 0)), count: 0};
      }
      bucket.t1 = t + (k > 1 ? 0.5 * k * c.dt : 0);
      colIdx.forEach((cs, ci) => cs.forEach((j, si) => {
        const v = c.data[row + j] * scale[ci][si];
        if (v < bucket.lo[ci][si]) bucket.lo[ci][si] = v;
        if (v > bucket.hi[ci][si]) bucket.hi[ci][si] = v;
        if (bucket.count === 0) bucket.first[ci][si] = v;
        bucket.last[ci][si] = v;
      }));
      bucket.count++;
    }
  }
  flush();
  if (k === 1) {  // one sample per point: no bucket pairs
    const keep = xs.map((_, i) => i % 2 === 0);
    return [xs.filter((_, i) => keep[i]), ys.map((cs) => cs.map((v) => v.filter((_, i) => keep[i])))];
  }
  return [xs, ys];
}

function currentView() {
  const dt = page.axis.cycle_s;
  const span = Math.round(parseFloat($("span").value) / dt);
  if (page.trigger.at !== null) {
    const pre = Math.round(span * 0.3);
    return [page.trigger.at - pre, page.trigger.at - pre + span];
  }
  return [page.lastSeq + 1 - span, page.lastSeq + 1];
}

function drawView(view, resetScales) {
  if (!view) return;
  const [xs, ys] = decimated(view[0], view[1], page.charts[0].bbox.width / devicePixelRatio || 800);
  page.view = view;
  page.charts.forEach((u, ci) => u.setData([xs, ...ys[ci]], resetScales));
  const link = $("win-download");
  link.href = api(`/recording.csv?from=${Math.max(0, view[0])}&to=${Math.min(view[1], page.lastSeq + 1)}`);
}

function draw() {
  if (page.lastSeq < 0) return;
  page.fullView = currentView();
  drawView(page.fullView, !page.zoomed);
}

function frame() {
  if (page.dirty && !page.paused && !page.zoomed) { page.dirty = false; draw(); }
  requestAnimationFrame(frame);
}

// ------------------------------------------------------------------------------------------------ cursors
// a click sets cursor A, the next B, the next A again; each sits on the sample nearest to the click
function setCursor(u) {
  if (u.cursor.left == null || u.cursor.left < 0) return;
  const seq = seqAtTime(u.posToVal(u.cursor.left, "x"));
  if (seq === null) return;
  page.cursors = page.cursors.length >= 2 ? [seq] : [...page.cursors, seq];
  showCursors();
  page.charts.forEach((c) => c.redraw(false));
}

function valuesAt(seq) {  // the signals of sample seq in the shown units, or null
  const s = sampleAt(seq);
  if (!s) return null;
  const [c, i] = s, out = {};
  page.cols.forEach((col, j) => { out[col] = c.data[i * c.cols + j] * CHANNELS[col][1]; });
  return out;
}

function showCursors() {
  const [a, b] = page.cursors;
  const ta = timeOf(a), tb = b === undefined ? null : timeOf(b);
  if (ta === null) return;
  const at = (seq, t) => `${t.toFixed(4)} s (sample ${seq})`;
  if (tb === null) {
    page.cursorReadout = {a: {seq: a, t: ta}, b: null};
    $("cursor-info").textContent = `A: ${at(a, ta)}; click again for B`;
    return;
  }
  const va = valuesAt(a), vb = valuesAt(b), dy = {};
  page.cols.filter((c) => c !== "statusword").forEach((c) => { dy[c] = vb[c] - va[c]; });
  page.cursorReadout = {a: {seq: a, t: ta}, b: {seq: b, t: tb}, dt_s: tb - ta, dy};
  $("cursor-info").textContent = `A: ${at(a, ta)}, B: ${at(b, tb)}; Δt = ${((tb - ta) * 1e3).toFixed(3)} ms; Δy: ` +
    Object.entries(dy).map(([c, v]) => `${CHANNELS[c][0]} ${v.toPrecision(6)} ${CHANNELS[c][2]}`).join(", ");
}

function drawCursors(u) {
  const ctx = u.ctx;
  page.cursors.forEach((seq, i) => {
    const t = timeOf(seq);
    if (t === null) return;
    const x = u.valToPos(t, "x", true);
    if (!(x >= u.bbox.left && x <= u.bbox.left + u.bbox.width)) return;
    ctx.save();
    ctx.strokeStyle = i === 0 ? "#e0245e" : "#17a";
    ctx.setLineDash([4, 3]);
    ctx.beginPath(); ctx.moveTo(x, u.bbox.top); ctx.lineTo(x, u.bbox.top + u.bbox.height); ctx.stroke();
    ctx.fillStyle = ctx.strokeStyle; ctx.fillText(i === 0 ? "A" : "B", x + 3, u.bbox.top + 12);
    ctx.restore();
  });
}

// ------------------------------------------------------------------------------------------------ trigger
function armTrigger() {
  const mode = $("trig-mode").value;
  page.trigger = {mode, armed: mode !== "none", at: null, bit: parseInt($("trig-bit").value, 10),
    chan: $("trig-chan").value, level: parseFloat($("trig-level").value), prev: null, fired: null};
  if (mode === "bit" && !(page.trigger.bit >= 0 && page.trigger.bit <= 15)) {
    $("trigger-status").textContent = "statusword bit must be 0..15"; page.trigger.armed = false; return;
  }
  if (mode === "threshold" && !Number.isFinite(page.trigger.level)) {
    $("trigger-status").textContent = "threshold level must be a number"; page.trigger.armed = false; return;
  }
  setPaused(false);
  $("trigger-status").textContent = page.trigger.armed ? `armed (${mode})` : "trigger off";
}

function checkTrigger(c) {
  const tr = page.trigger;
  if (tr.fired !== null && tr.at === null) {  // triggered: wait for the samples after it, then hold
    const post = Math.round(parseFloat($("span").value) / c.dt * 0.7);
    if (page.lastSeq >= tr.fired + post) {
      tr.at = tr.fired;
      page.paused = true;
      $("pause").textContent = "Run";
      drawView(currentView(), true);
    }
    return;
  }
  if (!tr.armed) return;
  const sw = page.cols.indexOf("statusword"), ch = page.cols.indexOf(tr.chan);
  const scale = tr.mode === "threshold" ? CHANNELS[tr.chan][1] : 1;
  for (let i = 0; i < c.n; i++) {
    let v;
    if (tr.mode === "fault") v = (c.data[i * c.cols + sw] & 0x8) !== 0;
    else if (tr.mode === "bit") v = ((c.data[i * c.cols + sw] >> tr.bit) & 1) === 1;
    else v = c.data[i * c.cols + ch] * scale > tr.level;
    if (v && tr.prev === false) {
      tr.armed = false;
      tr.fired = c.seq0 + i;
      const t = c.t0 + i * c.dt;
      $("trigger-status").textContent = `triggered at t = ${t.toFixed(4)} s (sample ${tr.fired})`;
      $("trigger-status").dataset.seq = String(tr.fired);
      return checkTrigger(c);
    }
    tr.prev = v;
  }
}

// ------------------------------------------------------------------------------------------------ recording
function toggleRecording() {
  const r = page.rec;
  if (r.from === null || r.to !== null) {
    page.rec = {from: page.lastSeq + 1, to: null};
    $("rec").textContent = "Stop";
    $("rec-status").textContent = `recording from sample ${page.rec.from}`;
    $("rec-download").hidden = true;
  } else {
    r.to = page.lastSeq + 1;
    $("rec").textContent = "Record";
    const n = r.to - r.from;
    $("rec-status").textContent = `recorded ${n} samples (${(n * page.axis.cycle_s).toFixed(3)} s)`;
    const link = $("rec-download");
    link.href = api(`/recording.csv?from=${r.from}&to=${r.to}`);
    link.download = `${page.axis.name}-recording.csv`;
    link.hidden = n <= 0;
  }
}

// ------------------------------------------------------------------------------------------------ injection
function setupInjection() {
  if (!page.axis.fault_injection) return;
  $("injection").hidden = false;
  $("inject-buttons").innerHTML = page.info.fault_kinds.map((k) =>
    `<button data-kind="${k}" class="inject">${k.replace(/_/g, " ")}</button>`).join(" ") +
    ' <button id="inject-clear">clear all</button>';
  document.querySelectorAll("button.inject").forEach((b) => { b.onclick = () => faultCommand({action: "inject", kind: b.dataset.kind}); });
  $("inject-clear").onclick = () => faultCommand({action: "clear"});
}

async function faultCommand(cmd) {
  const r = await fetch(api("/fault"), {method: "POST", headers: {"Content-Type": "application/json"}, body: JSON.stringify(cmd)});
  const body = await r.json();
  $("inject-result").textContent = r.ok ? `${cmd.action} ${cmd.kind || ""}: ok; active: ${body.active.join(", ") || "none"}` : `refused: ${body.error}`;
  $("inject-result").className = r.ok ? "result" : "result error";
}

// ------------------------------------------------------------------------------------------------ parameters
function setupParams() {
  $("od-mode").textContent = page.info.writable ? "writes go to the drive as SDO downloads" : "read-only (serve with --http-writable to write)";
  $("od-refresh").onclick = loadParams;
  $("od-filter").oninput = filterParams;
  loadParams();
}

async function loadParams() {
  const r = await fetch(api("/objects"));
  const body = await r.json();
  $("od").tBodies[0].innerHTML = body.objects.map((o) => {
    const w = page.info.writable && ["rw", "wo", "rwr", "rww"].includes(o.access);
    const val = o.value !== undefined ? o.value : o.read_abort ? `abort ${o.read_abort}` : o.access === "wo" ? "(write only)" : "";
    return `<tr data-key="${o.index}:${o.sub}" data-text="${esc((o.index + " " + o.name + " " + o.object).toLowerCase())}">` +
      `<td>${o.index}</td><td>${o.sub}</td><td>${esc(o.name)}</td><td>${o.type}</td><td>${o.access}</td>` +
      `<td class="val">${esc(val)}</td><td>${o.low ?? ""}</td><td>${o.high ?? ""}</td><td>${esc(o.note)}</td>` +
      `<td>${w ? `<input size="10" class="wv"> <button class="wb">write</button>` : ""}</td></tr>`;
  }).join("");
  document.querySelectorAll("#od button.wb").forEach((b) => { b.onclick = () => writeParam(b.closest("tr")); });
  filterParams();
}

function filterParams() {
  const f = $("od-filter").value.trim().toLowerCase().replace(/^0x/, "");
  document.querySelectorAll("#od tbody tr").forEach((tr) => { tr.hidden = f !== "" && !tr.dataset.text.includes(f); });
}

async function writeParam(tr) {
  const [index, sub] = tr.dataset.key.split(":");
  const text = tr.querySelector("input.wv").value.trim();
  const num = Number(text);
  const value = text !== "" && Number.isFinite(num) ? num : text;
  const r = await fetch(api("/write"), {method: "POST", headers: {"Content-Type": "application/json"},
    body: JSON.stringify({index, sub: parseInt(sub, 10), value})});
  const body = await r.json();
  const res = $("write-result");
  if (r.ok) { tr.querySelector(".val").textContent = body.value; res.textContent = `${index}:${sub} = ${body.value}`; res.className = "result"; }
  else { res.textContent = `${index}:${sub} refused: ${body.error}${body.abort_code ? ` (SDO abort ${body.abort_code})` : ""}`; res.className = "result error"; }
}

window.addEventListener("DOMContentLoaded", () => { main().catch((e) => { $("link-status").textContent = "error: " + e; }); });
