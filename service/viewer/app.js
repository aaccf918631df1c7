// CFSR live viewer: one WebSocket (binary frames + masks), REST for control and figures.
// No build step, no external resources.
"use strict";

(function () {
  // The access token (when the service has one) is traded once for an HttpOnly session
  // cookie (POST /api/session): it never goes into a URL, where servers log it.
  const $ = (id) => document.getElementById(id);

  // ---- state shared with tests (window.cfsrViewer) -------------------------------------------
  const state = {
    frames: 0, step: null, method: null, width: 0, height: 0, masks: [], maskPixels: {},
    statusUpdates: 0, lastStatus: null, connected: false, methods: {}, config: null,
    drawn: 0, limits: null,
  };
  window.cfsrViewer = state;

  // ---- REST helpers ----------------------------------------------------------------------------
  async function api(path, opts = {}) {
    const headers = Object.assign({}, opts.headers || {});
    if (opts.body !== undefined) headers["Content-Type"] = "application/json";
    const res = await fetch(path, {
      method: opts.method || "GET", headers, credentials: "same-origin",
      body: opts.body !== undefined ? JSON.stringify(opts.body) : undefined,
    });
    let data = null;
    try { data = await res.json(); } catch (e) { data = null; }
    if (!res.ok) {
      const d = data && data.detail;
      const detail = !d ? res.statusText : typeof d === "string" ? d
        : Array.isArray(d) ? d.map((e) => e.msg || JSON.stringify(e)).join("; ") : JSON.stringify(d);
      throw new Error(detail);
    }
    return data;
  }
  function msg(el, text, isError) {
    el.textContent = text || "";
    el.classList.toggle("error", !!isError);
  }

  // ---- colour maps -----------------------------------------------------------------------------
  const HEAT_ANCHORS = [[0,0,4],[40,11,84],[101,21,110],[159,42,99],[212,72,66],[245,125,21],[250,193,39],[252,255,164]];
  const HEAT = new Uint8Array(256 * 3);
  for (let i = 0; i < 256; i++) {
    const x = i / 255 * (HEAT_ANCHORS.length - 1);
    const k = Math.min(HEAT_ANCHORS.length - 2, Math.floor(x));
    const f = x - k;
    for (let c = 0; c < 3; c++) HEAT[i * 3 + c] = Math.round(HEAT_ANCHORS[k][c] * (1 - f) + HEAT_ANCHORS[k + 1][c] * f);
  }
  const COARSE = [255, 64, 64], FINE = [64, 255, 96], ALPHA = 0.45;
  (function drawLegend() {
    const ctx = $("legend-bar").getContext("2d");
    const img = ctx.createImageData(256, 12);
    for (let y = 0; y < 12; y++) for (let x = 0; x < 256; x++) {
      const o = (y * 256 + x) * 4;
      img.data[o] = HEAT[x * 3]; img.data[o + 1] = HEAT[x * 3 + 1]; img.data[o + 2] = HEAT[x * 3 + 2]; img.data[o + 3] = 255;
    }
    ctx.putImageData(img, 0, 0);
  })();

  // ---- frame decoding and drawing -------------------------------------------------------------
  const canvas = $("frame");
  const ctx = canvas.getContext("2d");
  let latest = null;      // newest decoded message, drawn on the next animation frame
  let imageData = null;
  let dirty = false;
  const fpsTimes = [];

  function decode(buf) {
    const dv = new DataView(buf);
    const magic = String.fromCharCode(dv.getUint8(0), dv.getUint8(1), dv.getUint8(2), dv.getUint8(3));
    if (magic !== "CFSR") throw new Error("bad frame magic " + magic);
    const hlen = dv.getUint16(6, true);
    const step = Number(dv.getBigInt64(8, true));
    const frameNo = dv.getUint32(16, true);
    const w = dv.getUint16(20, true), h = dv.getUint16(22, true);
    const flags = dv.getUint8(24);
    const gain = dv.getFloat32(28, true);
    const computeMs = dv.getFloat32(32, true), latencyMs = dv.getFloat32(36, true);
    let name = "";
    for (let i = 40; i < 64; i++) { const c = dv.getUint8(i); if (!c) break; name += String.fromCharCode(c); }
    const n = w * h, nb = (n + 7) >> 3;
    const image = new Uint8Array(buf, hlen, n);
    const coarse = (flags & 1) ? new Uint8Array(buf, hlen + n, nb) : null;
    const fine = (flags & 2) ? new Uint8Array(buf, hlen + n + nb, nb) : null;
    return { step, frameNo, w, h, gain, computeMs, latencyMs, method: name, image, coarse, fine };
  }

  function render() {
    if (dirty && latest) {
      const f = latest;
      if (canvas.width !== f.w || canvas.height !== f.h || !imageData) {
        canvas.width = f.w; canvas.height = f.h;
        imageData = ctx.createImageData(f.w, f.h);
        applyZoom();
      }
      const heat = document.querySelector('input[name="view"]:checked').value === "heat";
      const showC = $("ov-coarse").checked && f.coarse, showF = $("ov-fine").checked && f.fine;
      const d = imageData.data, img = f.image, n = f.w * f.h;
      for (let p = 0, o = 0; p < n; p++, o += 4) {
        const v = img[p];
        let r, g, b;
        if (heat) { r = HEAT[v * 3]; g = HEAT[v * 3 + 1]; b = HEAT[v * 3 + 2]; } else { r = g = b = v; }
        if (showC && (f.coarse[p >> 3] >> (p & 7)) & 1) {
          r = r * (1 - ALPHA) + COARSE[0] * ALPHA; g = g * (1 - ALPHA) + COARSE[1] * ALPHA; b = b * (1 - ALPHA) + COARSE[2] * ALPHA;
        }
        if (showF && (f.fine[p >> 3] >> (p & 7)) & 1) {
          r = r * (1 - ALPHA) + FINE[0] * ALPHA; g = g * (1 - ALPHA) + FINE[1] * ALPHA; b = b * (1 - ALPHA) + FINE[2] * ALPHA;
        }
        d[o] = r; d[o + 1] = g; d[o + 2] = b; d[o + 3] = 255;
      }
      ctx.putImageData(imageData, 0, 0);
      dirty = false;
      state.drawn++;
      $("no-frame").classList.add("hidden");
    }
    requestAnimationFrame(render);
  }
  requestAnimationFrame(render);

  function applyZoom() {
    const z = Number($("zoom").value);
    canvas.style.width = canvas.width * z + "px";
    canvas.style.height = canvas.height * z + "px";
  }
  $("zoom").addEventListener("change", applyZoom);
  for (const el of document.querySelectorAll('input[name="view"], #ov-coarse, #ov-fine')) {
    el.addEventListener("change", () => {
      $("legend").classList.toggle("hidden", document.querySelector('input[name="view"]:checked').value !== "heat");
      dirty = true;
    });
  }

  function popcount(bits) {
    if (!bits) return 0;
    let n = 0;
    for (let i = 0; i < bits.length; i++) { let v = bits[i]; while (v) { v &= v - 1; n++; } }
    return n;
  }

  function onFrame(f) {
    latest = f; dirty = true;
    state.frames++; state.step = f.step; state.method = f.method; state.width = f.w; state.height = f.h;
    state.masks = [f.coarse ? "coarse" : null, f.fine ? "fine" : null].filter(Boolean);
    state.maskPixels = { coarse: popcount(f.coarse), fine: popcount(f.fine) };
    const now = performance.now();
    fpsTimes.push(now);
    while (fpsTimes.length && now - fpsTimes[0] > 2000) fpsTimes.shift();
    $("frame-step").textContent = f.step;
    $("frame-method").textContent = f.method;
    $("frame-count").textContent = state.frames;
    $("frame-masks").textContent = state.masks.length ? state.masks.join(", ") : "none";
    $("viewer-fps").textContent = (fpsTimes.length / 2).toFixed(1);
    $("legend-max").textContent = f.gain.toFixed(3);
    $("ov-coarse").disabled = !f.coarse;
    $("ov-fine").disabled = !f.fine;
  }

  // ---- WebSocket with reconnect -----------------------------------------------------------------
  let backoff = 250;
  function connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const url = proto + "//" + location.host + "/ws";
    const ws = new WebSocket(url);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { backoff = 250; state.connected = true; setConn(true); };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") return;
      try { onFrame(decode(ev.data)); } catch (e) { console.error(e); }
    };
    ws.onclose = () => {
      state.connected = false; setConn(false);
      setTimeout(connect, backoff); backoff = Math.min(5000, backoff * 2);
    };
    ws.onerror = () => ws.close();
  }
  function setConn(on) {
    const el = $("conn");
    el.textContent = on ? "live" : "disconnected";
    el.classList.toggle("on", on); el.classList.toggle("off", !on);
  }

  // ---- methods and parameters ---------------------------------------------------------------------
  function buildParams(name, values) {
    const form = $("params-form");
    form.innerHTML = "";
    const m = state.methods[name];
    $("method-summary").textContent = m ? (m.summary + (m.reference ? " (" + m.reference + ")" : "")) : "";
    if (!m) return;
    for (const [key, p] of Object.entries(m.params)) {
      const label = document.createElement("label");
      label.textContent = key + (p.unit ? " [" + p.unit + "]" : "");
      label.title = p.help;
      label.htmlFor = "param-" + key;
      let input;
      const v = values && key in values ? values[key] : p.default;
      if (typeof p.default === "boolean") {
        input = document.createElement("input"); input.type = "checkbox"; input.checked = !!v;
      } else if (typeof p.default === "number") {
        input = document.createElement("input"); input.type = "number"; input.step = "any"; input.value = v;
      } else {
        input = document.createElement("input"); input.type = "text"; input.value = v;
      }
      input.id = "param-" + key; input.name = key; input.title = p.help;
      input.dataset.kind = typeof p.default;
      form.appendChild(label); form.appendChild(input);
    }
  }
  function readParams() {
    const out = {};
    for (const el of $("params-form").querySelectorAll("input")) {
      if (el.dataset.kind === "boolean") out[el.name] = el.checked;
      else if (el.dataset.kind === "number") out[el.name] = Number(el.value);
      else out[el.name] = el.value;
    }
    return out;
  }
  async function loadMethods() {
    const list = await api("/api/methods");
    const sel = $("method-select");
    sel.innerHTML = "";
    for (const m of list) {
      state.methods[m.name] = m;
      const o = document.createElement("option");
      o.value = m.name; o.textContent = m.name + (m.masks.length ? " (masks)" : "");
      sel.appendChild(o);
    }
  }
  // ---- limits: the service's own bounds (GET /api/limits), written once on the server -------
  let recordNameRe = null;
  async function loadLimits() {
    const lim = await api("/api/limits");
    state.limits = lim;
    $("max-fps").min = lim.max_fps.minimum;
    $("max-fps").max = lim.max_fps.maximum;
    recordNameRe = new RegExp(lim.recording_name_pattern);
    $("record-name").title = "file name, .dat added; must match " + lim.recording_name_pattern;
    $("max-fps").title = lim.max_fps.minimum + " to " + lim.max_fps.maximum + " frames/s";
    checkRecordName();
  }
  // a custom validity, not the pattern attribute: browsers compile that with the v flag,
  // which refuses a plain "-" at the end of a character class
  function checkRecordName() {
    const el = $("record-name"), v = el.value.trim();
    el.setCustomValidity(!v || !recordNameRe || recordNameRe.test(v) ? ""
      : "not a recording name: it must match " + recordNameRe.source);
    return el.checkValidity();
  }
  $("record-name").addEventListener("input", checkRecordName);

  async function loadConfig() {
    const c = await api("/api/config");
    state.config = c;
    $("method-select").value = c.method;
    buildParams(c.method, c.params);
    $("gain-mode").value = c.display.gain_mode;
    if (c.display.gain) $("gain").value = c.display.gain;
    else if (c.effective_gain) $("gain").value = c.effective_gain;
    $("max-fps").value = c.max_fps;
  }
  $("method-select").addEventListener("change", () => {
    const name = $("method-select").value;
    buildParams(name, state.config && state.config.method === name ? state.config.params : null);
  });
  async function applyConfig() {
    const method = $("method-select").value;
    const body = {
      method, params: readParams(),
      display: { gain_mode: $("gain-mode").value, gain: Number($("gain").value) || null },
      max_fps: Number($("max-fps").value) || 30,
    };
    try {
      const c = await api("/api/config", { method: "PUT", body });
      state.config = c;
      buildParams(c.method, c.params);
      msg($("config-msg"), "applied: " + c.method);
    } catch (e) { msg($("config-msg"), e.message, true); }
  }
  $("apply-config").addEventListener("click", applyConfig);

  // ---- sources ----------------------------------------------------------------------------------------
  async function loadSources() {
    const list = await api("/api/sources");
    const sel = $("source-select");
    sel.innerHTML = "";
    for (const s of list) {
      const o = document.createElement("option");
      o.value = s.id;
      let label = s.name;
      if (s.duration_s) label += " (" + s.duration_s.toFixed(2) + " s)";
      if (s.note) label += " - " + s.note;
      o.textContent = label;
      if (s.current) o.selected = true;
      sel.appendChild(o);
    }
  }
  $("source-open").addEventListener("click", async () => {
    try {
      await api("/api/source", { method: "PUT", body: { id: $("source-select").value } });
      await loadConfig();
      msg($("replay-msg"), "");
    } catch (e) { msg($("replay-msg"), e.message, true); }
  });

  // ---- replay controls ----------------------------------------------------------------------------
  let seeking = false;
  async function replay(method, path, body) {
    try { return await api(path, { method, body }); }
    catch (e) { msg($("replay-msg"), e.message, true); return null; }
  }
  $("play").addEventListener("click", () => replay("PUT", "/api/replay", { playing: true }));
  $("pause").addEventListener("click", () => replay("PUT", "/api/replay", { playing: false }));
  $("step").addEventListener("click", () => replay("POST", "/api/replay/step", { n: 256 }));
  $("loop").addEventListener("change", () => replay("PUT", "/api/replay", { loop: $("loop").checked }));
  $("speed").addEventListener("change", () => replay("PUT", "/api/replay", { speed: Number($("speed").value) }));
  $("seek").addEventListener("input", () => { seeking = true; });
  $("seek").addEventListener("change", async () => {
    await replay("POST", "/api/replay/seek", { position: Number($("seek").value) });
    seeking = false;
  });

  function showReplay(r) {
    const panel = $("replay-panel");
    const enabled = !!r;
    for (const el of panel.querySelectorAll("button, input, select")) el.disabled = !enabled;
    if (!r) { $("position").textContent = "-"; $("n-frames").textContent = "-"; $("position-s").textContent = "-";
      msg($("replay-msg"), "this source has no replay controls"); return; }
    if ($("replay-msg").textContent === "this source has no replay controls") msg($("replay-msg"), "");
    $("seek").max = Math.max(0, r.end - 1); $("seek").min = r.start;
    if (!seeking) $("seek").value = r.position;
    $("position").textContent = r.position; $("n-frames").textContent = r.n_frames;
    $("position-s").textContent = (r.position / r.rate_hz).toFixed(4);
    $("play").classList.toggle("active", r.playing);
    if (document.activeElement !== $("speed")) {
      const opt = [...$("speed").options].find((o) => Number(o.value) === r.speed);
      if (opt) $("speed").value = opt.value;
    }
    if (document.activeElement !== $("loop")) $("loop").checked = r.loop;
  }

  // ---- recording ----------------------------------------------------------------------------------------
  let recording = false;
  $("record").addEventListener("click", async () => {
    try {
      if (!recording) {
        if (!checkRecordName()) { msg($("record-msg"), $("record-name").validationMessage, true); return; }
        const name = $("record-name").value.trim() || undefined;
        await api("/api/record", { method: "POST", body: { action: "start", name } });
      } else {
        const r = await api("/api/record", { method: "POST", body: { action: "stop" } });
        msg($("record-msg"), "saved " + r.name + ": " + r.frames + " frames, lost " + r.lost_frames);
      }
    } catch (e) { msg($("record-msg"), e.message, true); }
  });
  function showRecord(r) {
    recording = !!r.recording;
    $("record").textContent = recording ? "Stop" : "Start";
    $("record").classList.toggle("recording", recording);
    if (recording) msg($("record-msg"), "recording " + r.name + ": " + r.frames + " frames, " + (r.bytes / 1e6).toFixed(0) + " MB, lost " + r.lost_frames);
  }

  // ---- live figures ---------------------------------------------------------------------------------------
  const fmt = (x, d = 1) => (x === null || x === undefined || !isFinite(x)) ? "-" : Number(x).toFixed(d);
  const big = (x) => (x === null || x === undefined) ? "-" : Math.round(x).toLocaleString("en-US");
  // worker skips are by design (it only needs the newest window), so they are not shown as errors
  function setDrop(id, v, neutral) { const el = $(id); el.textContent = big(v); el.classList.toggle("nonzero", v > 0 && !neutral); }
  // the background compilation of a first start (service/kernels.py): which methods are ready
  function kernelNote(k) {
    if (!k || k.state !== "compiling") return k && k.state === "failed" ? "; kernel warm-up failed: " + k.error : "";
    const n = k.ready.length + k.pending.length;
    return "; compiling kernels in the background (" + k.ready.length + "/" + n + " methods ready"
      + (k.pending.length ? ", now " + k.pending[0] : "") + ", " + Math.round(k.elapsed_s || 0) + " s)";
  }
  async function pollStatus() {
    try {
      const s = await api("/api/status");
      state.lastStatus = s; state.statusUpdates++;
      $("fig-input").textContent = big(s.input_steps_per_s);
      $("fig-rtf").textContent = fmt(s.real_time_factor, 3);
      $("fig-worker-rate").textContent = big(s.worker.steps_per_s);
      $("fig-fps").textContent = fmt(s.output_fps, 1);
      $("fig-latency").textContent = fmt(s.latency_ms, 1);
      $("fig-compute").textContent = fmt(s.compute_ms, 1);
      $("fig-worker").textContent = (s.worker.alive ? "alive" : "down") + ", restarts " + s.worker.restarts
        + (s.worker.first_frame_s > 3
          ? "; first " + s.method + " frame for " + Math.round(s.worker.first_frame_s)
            + " s: numba compiles the kernels on first use on this machine (once, cached)"
          : "")
        + kernelNote(s.kernels);
      setDrop("drop-usb", s.drops.usb); setDrop("drop-replay", s.drops.replay);
      setDrop("drop-ring", s.drops.ring); setDrop("drop-worker", s.drops.worker, true);
      setDrop("drop-clients", s.drops.clients); setDrop("drop-recorder", s.drops.recorder);
      const me = s.drops.per_client.filter((c) => c.kind === "ws");
      setDrop("drop-me", me.length === 1 ? me[0].dropped : me.reduce((a, c) => a + c.dropped, 0));
      $("status-count").textContent = state.statusUpdates;
      const st = $("source-state");
      st.textContent = (s.source.kind || "?") + ": " + (s.source.state || "?");
      st.classList.toggle("on", s.source.state === "streaming");
      st.classList.toggle("off", ["disconnected", "backoff", "error"].includes(s.source.state));
      showReplay(s.source.replay);
      showRecord(s.recording);
      if (state.config && state.config.method !== s.method) await loadConfig();
      msg($("status-msg"), s.source.last_error ? "source: " + s.source.last_error : "");
    } catch (e) { msg($("status-msg"), "status: " + e.message, true); }
    setTimeout(pollStatus, 1000);
  }

  // ---- start -------------------------------------------------------------------------------------------------
  // ---- session: ask for the token once when the service needs one -----------------------------
  async function login(token) {
    return api("/api/session", { method: "POST", body: { token } });
  }
  function askToken(error) {
    return new Promise((resolve) => {
      const box = $("login");
      box.classList.remove("hidden");
      msg($("login-msg"), error || "", !!error);
      $("login-token").focus();
      $("login-form").onsubmit = (ev) => {
        ev.preventDefault();
        box.classList.add("hidden");
        resolve($("login-token").value);
      };
    });
  }
  async function ensureSession() {
    let s = await api("/api/session");
    // a token in the fragment (#token=...) is never sent to the server; use it once, then drop it
    const fromHash = new URLSearchParams(location.hash.slice(1)).get("token");
    if (fromHash) history.replaceState(null, "", location.pathname + location.search);
    let error = null;
    let candidate = fromHash;
    while (s.token_required && !s.authenticated) {
      const token = candidate || await askToken(error);
      candidate = null;
      try { s = await login(token); } catch (e) { error = "wrong token"; }
    }
    $("login-token").value = "";
  }

  (async function init() {
    await ensureSession();
    connect();
    try { await loadLimits(); await loadMethods(); await loadConfig(); await loadSources(); }
    catch (e) { msg($("config-msg"), e.message, true); }
    pollStatus();
  })();
})();
