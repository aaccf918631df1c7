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
    drawn: 0, limits: null, applied: 0, compare: false, pinned: null, lastSnapshot: null,
  };
  window.cfsrViewer = state;

  // ---- REST helpers ----------------------------------------------------------------------------
  // An error carries every entry of a 422 answer (`details`: [{loc, msg}]), so the form can
  // put each one beside its own field instead of showing the first as one line.
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
      const details = !d ? [{ loc: [], msg: res.statusText }] : typeof d === "string" ? [{ loc: [], msg: d }]
        : Array.isArray(d) ? d.map((e) => ({ loc: e.loc || [], msg: e.msg || JSON.stringify(e) }))
          : [{ loc: [], msg: JSON.stringify(d) }];
      const err = new Error(details.map((e) => e.msg).join("; "));
      err.details = details;
      err.status = res.status;
      throw err;
    }
    data = data || {};
    data.__status = res.status;
    return data;
  }
  function msg(el, text, isError) {
    el.textContent = text || "";
    el.classList.toggle("error", !!isError);
  }

  // ---- colour maps -----------------------------------------------------------------------------
  // The frame schema (GET /api/schema) is the server's: the message header's offsets, the mask
  // planes' names in order with their colours and meanings, and the heat colour map. Where two
  // masks hold, the later plane is painted (fine over coarse: the finer statement), so two
  // masks never blend into a third colour.
  let SCHEMA = null, MASKS = [], ALPHA = 0.4;
  const HEAT = new Uint8Array(256 * 3);
  const maskBox = (name) => $("ov-" + name);
  async function loadSchema() {
    SCHEMA = await api("/api/schema");
    HEAT.set(SCHEMA.heat_lut);
    MASKS = SCHEMA.masks;
    ALPHA = SCHEMA.mask_alpha;
    const holder = $("mask-boxes");
    holder.textContent = "";
    for (const m of MASKS) {
      const label = document.createElement("label");
      label.className = "mask";
      label.title = m.meaning || (m.name + " mask");
      const box = document.createElement("input");
      box.type = "checkbox"; box.id = "ov-" + m.name; box.disabled = true;
      box.addEventListener("change", overlaysChanged);
      const sw = document.createElement("i");
      sw.className = "swatch"; sw.style.background = "rgb(" + m.color.join(",") + ")";
      label.append(box, " ", sw, " " + m.name + " mask");
      holder.append(label);
    }
    drawLegend();
  }
  function drawLegend() {
    const lctx = $("legend-bar").getContext("2d");
    const img = lctx.createImageData(256, 10);
    for (let y = 0; y < 10; y++) for (let x = 0; x < 256; x++) {
      const o = (y * 256 + x) * 4;
      img.data[o] = HEAT[x * 3]; img.data[o + 1] = HEAT[x * 3 + 1]; img.data[o + 2] = HEAT[x * 3 + 2]; img.data[o + 3] = 255;
    }
    lctx.putImageData(img, 0, 0);
  }

  // ---- frame decoding and drawing -------------------------------------------------------------
  const canvas = $("frame");
  const ctx = canvas.getContext("2d");
  const pinCanvas = $("pinned");
  const pinCtx = pinCanvas.getContext("2d");
  let latest = null;      // newest decoded message, drawn on the next animation frame
  let dirty = false;
  const fpsTimes = [];

  function decode(buf) {
    const dv = new DataView(buf), O = SCHEMA.ws_offsets;
    const magic = String.fromCharCode(dv.getUint8(0), dv.getUint8(1), dv.getUint8(2), dv.getUint8(3));
    if (magic !== "CFSR") throw new Error("bad frame magic " + magic);
    if (dv.getUint16(O.version, true) !== SCHEMA.ws_version) throw new Error("frame version differs from the schema's");
    const hlen = dv.getUint16(O.header_bytes, true);
    const step = Number(dv.getBigInt64(O.step, true));
    const frameNo = dv.getUint32(O.frame_no, true);
    const w = dv.getUint16(O.width, true), h = dv.getUint16(O.height, true);
    const flags = dv.getUint8(O.mask_flags);
    const gain = dv.getFloat32(O.gain, true);
    const computeMs = dv.getFloat32(O.compute_ms, true), latencyMs = dv.getFloat32(O.latency_ms, true);
    const quality = SCHEMA.quality_tiers[dv.getUint8(O.quality)] || "";
    let name = "";
    for (let i = O.method; i < O.method + SCHEMA.method_name_bytes; i++) { const c = dv.getUint8(i); if (!c) break; name += String.fromCharCode(c); }
    const n = w * h, nb = (n + 7) >> 3;
    const image = new Uint8Array(buf, hlen, n);
    const masks = {};
    MASKS.forEach((m, k) => { if (flags & (1 << k)) masks[m.name] = new Uint8Array(buf, hlen + n + k * nb, nb); });
    return { step, frameNo, w, h, gain, computeMs, latencyMs, method: name, quality, image, masks };
  }

  const bit = (plane, p) => (plane[p >> 3] >> (p & 7)) & 1;
  function paint(f, target, tctx) {
    if (target.width !== f.w || target.height !== f.h) { target.width = f.w; target.height = f.h; fit(); }
    const imageData = tctx.createImageData(f.w, f.h);
    const heat = document.querySelector('input[name="view"]:checked').value === "heat";
    // the checked masks this frame has, the last plane first (it is painted over the others)
    const shown = MASKS.filter((m) => f.masks[m.name] && maskBox(m.name).checked).reverse();
    const d = imageData.data, img = f.image, n = f.w * f.h;
    for (let p = 0, o = 0; p < n; p++, o += 4) {
      const v = img[p];
      let r, g, b;
      if (heat) { r = HEAT[v * 3]; g = HEAT[v * 3 + 1]; b = HEAT[v * 3 + 2]; } else { r = g = b = v; }
      let m = null;
      for (let k = 0; k < shown.length && !m; k++) if (bit(f.masks[shown[k].name], p)) m = shown[k].color;
      if (m) { r = r * (1 - ALPHA) + m[0] * ALPHA; g = g * (1 - ALPHA) + m[1] * ALPHA; b = b * (1 - ALPHA) + m[2] * ALPHA; }
      d[o] = r; d[o + 1] = g; d[o + 2] = b; d[o + 3] = 255;
    }
    tctx.putImageData(imageData, 0, 0);
  }

  function render() {
    if (dirty && latest) {
      paint(latest, canvas, ctx);
      if (state.pinned && state.pinned.redraw) { paint(state.pinned.frame, pinCanvas, pinCtx); state.pinned.redraw = false; }
      dirty = false;
      state.drawn++;
      $("no-frame").classList.add("hidden");
      showCompareLabels();
    }
    requestAnimationFrame(render);
  }
  requestAnimationFrame(render);

  // ---- the picture fills the space it has ("fit"), or a fixed zoom ----------------------------
  function fit() {
    const stage = $("stage");
    const w = canvas.width, h = canvas.height;
    const z = $("zoom").value;
    let scale;
    if (z === "fit") {
      const sw = stage.clientWidth - 8, sh = stage.clientHeight - 8;
      scale = Math.max(0.25, Math.min(sw / w, sh / h));
    } else scale = Number(z);
    for (const c of [canvas, pinCanvas]) {
      c.style.width = Math.floor(w * scale) + "px";
      c.style.height = Math.floor(h * scale) + "px";
    }
    setSplit();
  }
  $("zoom").addEventListener("change", fit);
  new ResizeObserver(fit).observe($("stage"));
  function overlaysChanged() {
    $("legend").classList.toggle("hidden", document.querySelector('input[name="view"]:checked').value !== "heat");
    if (state.pinned) state.pinned.redraw = true;
    dirty = true;
  }
  for (const el of document.querySelectorAll('input[name="view"]')) el.addEventListener("change", overlaysChanged);

  function popcount(bits) {
    if (!bits) return 0;
    let n = 0;
    for (let i = 0; i < bits.length; i++) { let v = bits[i]; while (v) { v &= v - 1; n++; } }
    return n;
  }

  function onFrame(f) {
    latest = f; dirty = true;
    state.frames++; state.step = f.step; state.method = f.method; state.width = f.w; state.height = f.h;
    state.masks = MASKS.map((m) => m.name).filter((nm) => f.masks[nm]);
    state.maskPixels = Object.fromEntries(MASKS.map((m) => [m.name, popcount(f.masks[m.name])]));
    const now = performance.now();
    fpsTimes.push(now);
    while (fpsTimes.length && now - fpsTimes[0] > 2000) fpsTimes.shift();
    $("frame-step").textContent = f.step;
    $("frame-method").textContent = f.method;
    $("frame-count").textContent = state.frames;
    $("frame-masks").textContent = state.masks.length ? state.masks.join(", ") : "none";
    $("viewer-fps").textContent = (fpsTimes.length / 2).toFixed(1);
    $("legend-max").textContent = f.gain.toFixed(3);
    for (const m of MASKS) maskBox(m.name).disabled = !f.masks[m.name];
    for (const w of frameWaiters.splice(0)) w(f);
    if (state.pinned) alignCompare(f);
  }
  const frameWaiters = [];
  const nextFrame = () => new Promise((resolve) => frameWaiters.push(resolve));

  // ---- WebSocket with reconnect -----------------------------------------------------------------
  let backoff = 250;
  function connect() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const ws = new WebSocket(proto + "//" + location.host + "/ws");
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
  // Parameters people change are shown; the rest are grouped by the stage they tune and
  // collapsed. The groups follow the Param tables' naming (a parameter no rule names lands in
  // "other", so a new one is never hidden).
  const MAIN = ["tfp_window", "distinction", "phi0", "pm_count", "adaptive"];
  const FLAT_UP_TO = 6;   // a method with this many parameters or fewer shows them all
  const GROUPS = [
    ["coarse distinction and static rate", /^(T|theta|tfp_.*|max_isi|static_estimator|static_span|steady_.*|distinction|coarse_close|dynamic_.*)$/],
    ["fine distinction (MOG, DAISI, still pixels)", /^(mog_.*|still_.*|phi0|phi|daisi_span|close_size|min_area|dilate)$/],
    ["PatchMatch", /^pm_.*$/],
    ["adaptive (skip what the scene does not need)", /^(adaptive|static_tol|static_tile|static_window)$/],
    ["slow motion (long windows where the scene moves slowly)", /^slow_.*$/],
    ["carried work (outputs close in time)", /^carry_.*$/],
  ];
  const QUALITY = "quality";

  function paramDefaults(m) {
    const out = {};
    for (const [k, p] of Object.entries(m.params)) out[k] = p.default;
    return out;
  }
  function fieldFor(key, p, v) {
    const label = document.createElement("label");
    label.textContent = key + (p.unit ? " [" + p.unit + "]" : "");
    label.title = p.help + (p.range ? " (" + p.range + ")" : "");
    label.htmlFor = "param-" + key;
    let input;
    if (p.choices && p.choices.length) {
      input = document.createElement("select");
      for (const c of p.choices) { const o = document.createElement("option"); o.value = c; o.textContent = c; input.appendChild(o); }
      input.value = v; input.dataset.kind = "choice";
    } else if (typeof p.default === "boolean") {
      input = document.createElement("input"); input.type = "checkbox"; input.checked = !!v; input.dataset.kind = "boolean";
    } else if (typeof p.default === "number") {
      input = document.createElement("input"); input.type = "number"; input.step = "any"; input.value = v; input.dataset.kind = "number";
      if (p.minimum !== null && p.minimum !== undefined) input.min = p.minimum;
      if (p.maximum !== null && p.maximum !== undefined) input.max = p.maximum;
    } else {
      input = document.createElement("input"); input.type = "text"; input.value = v; input.dataset.kind = "text";
    }
    input.id = "param-" + key; input.name = key; input.title = label.title;
    input.classList.add("param");
    const wrap = document.createElement("span");
    wrap.className = "field";
    const err = document.createElement("span");
    err.className = "field-err"; err.id = "err-param-" + key;
    wrap.appendChild(input); wrap.appendChild(err);
    input.addEventListener(input.tagName === "SELECT" || input.type === "checkbox" ? "change" : "input", () => {
      checkField(input); markPreset(); scheduleApply();
    });
    return [label, wrap];
  }

  // values: the method's parameters; tier: CFSR's live tier (the config's own quality field)
  function buildParams(name, values, tier) {
    const form = $("params-form"), groups = $("param-groups");
    form.innerHTML = ""; groups.innerHTML = "";
    const m = state.methods[name];
    $("method-summary").textContent = m ? (m.summary + (m.reference ? " (" + m.reference + ")" : "")) : "";
    if (!m) return;
    const vals = Object.assign(paramDefaults(m), values || {});
    const keys = Object.keys(m.params).filter((k) => k !== QUALITY);
    const flat = keys.length <= FLAT_UP_TO;
    const buckets = GROUPS.map(([title]) => ({ title, keys: [] }));
    const other = { title: "other", keys: [] };
    for (const k of keys) {
      if (flat || MAIN.includes(k)) { form.append(...fieldFor(k, m.params[k], vals[k])); continue; }
      const i = GROUPS.findIndex(([, re]) => re.test(k));
      (i >= 0 ? buckets[i] : other).keys.push(k);
    }
    for (const b of [...buckets, other]) {
      if (!b.keys.length) continue;
      const det = document.createElement("details");
      det.className = "group";
      const sum = document.createElement("summary");
      sum.innerHTML = "";
      sum.append(b.title + " ");
      const c = document.createElement("span"); c.className = "count"; c.textContent = "(" + b.keys.length + ")";
      sum.appendChild(c);
      const body = document.createElement("div"); body.className = "group-body";
      for (const k of b.keys) body.append(...fieldFor(k, m.params[k], vals[k]));
      det.append(sum, body);
      groups.appendChild(det);
    }
    // the quality tier (CFSR's speed tiers) and the library's presets come first
    const qsel = $("quality-select"), hasQ = QUALITY in m.params;
    $("quality-label").classList.toggle("hidden", !hasQ); qsel.classList.toggle("hidden", !hasQ);
    qsel.innerHTML = "";
    if (hasQ) {
      // the live service adds "auto" (it picks the tier per frame to hold max fps)
      const choices = ["auto", ...(m.params[QUALITY].choices || []).filter((c) => c !== "auto")];
      for (const c of choices) { const o = document.createElement("option"); o.value = c; o.textContent = c; qsel.appendChild(o); }
      qsel.value = tier || "auto";
    }
    const psel = $("preset-select");
    psel.innerHTML = "";
    for (const p of ["defaults", ...Object.keys(m.presets || {}), "custom"]) {
      const o = document.createElement("option"); o.value = p; o.textContent = p;
      if (p === "custom") o.disabled = true;
      psel.appendChild(o);
    }
    markPreset();
  }

  // the preset whose values the form holds, else "custom"
  function markPreset() {
    const m = state.methods[$("method-select").value];
    if (!m) return;
    const cur = readParams();
    const base = paramDefaults(m);
    const same = (want) => Object.keys(m.params).every((k) => k === QUALITY || String(cur[k]) === String(want[k]));
    let name = "custom";
    if (same(base)) name = "defaults";
    else for (const [p, vals] of Object.entries(m.presets || {})) if (same(Object.assign({}, base, vals))) { name = p; break; }
    $("preset-select").value = name;
  }

  function readParams() {
    const out = {};
    for (const el of document.querySelectorAll(".param")) {
      if (el.dataset.kind === "boolean") out[el.name] = el.checked;
      else if (el.dataset.kind === "number") out[el.name] = el.value.trim() === "" ? NaN : Number(el.value);
      else out[el.name] = el.value;
    }
    return out;
  }
  // CFSR's live tier: the config's own field, not a parameter (null: the method has none)
  function readTier() {
    const m = state.methods[$("method-select").value];
    return m && QUALITY in m.params ? $("quality-select").value : null;
  }

  // ---- field checks: the Param table's bounds, beside the field --------------------------------
  function fieldError(id, text) {
    const err = $("err-" + id);
    const input = id === "max_fps" ? $("max-fps") : $(id);
    if (err) err.textContent = text || "";
    if (input) input.classList.toggle("invalid", !!text);
    return !text;
  }
  function rangeText(lo, hi, unit) { return lo + ".." + hi + (unit ? " " + unit : ""); }
  function checkNumber(v, lo, hi, unit) {
    if (!isFinite(v)) return "a number is needed";
    if (lo !== null && lo !== undefined && v < lo) return "must be >= " + lo + " (" + rangeText(lo, hi, unit) + ")";
    if (hi !== null && hi !== undefined && v > hi) return "must be <= " + hi + " (" + rangeText(lo, hi, unit) + ")";
    return "";
  }
  function checkField(input) {
    const m = state.methods[$("method-select").value];
    const p = m && m.params[input.name];
    if (!p) return true;
    let text = "";
    if (input.dataset.kind === "number") {
      text = checkNumber(input.value.trim() === "" ? NaN : Number(input.value), p.minimum, p.maximum, p.unit);
    } else if (input.dataset.kind === "choice" && p.choices && !p.choices.includes(input.value)) {
      text = "one of " + p.choices.join(", ");
    }
    return fieldError("param-" + input.name, text);
  }
  function checkDisplay() {
    let ok = true;
    const lim = state.limits && state.limits.max_fps;
    ok = fieldError("max_fps", checkNumber(Number($("max-fps").value), lim ? lim.minimum : 0, lim ? lim.maximum : null, "frames/s")) && ok;
    const fixed = $("gain-mode").value === "fixed";
    const g = $("gain").value.trim();
    ok = fieldError("gain", !fixed && g === "" ? "" : checkNumber(Number(g), 0.000001, 1, "spikes/step")) && ok;
    return ok;
  }
  function checkAll() {
    let ok = checkDisplay();
    for (const el of document.querySelectorAll(".param")) ok = checkField(el) && ok;
    return ok;
  }
  // a server answer (422) put beside the fields it names; what names no field goes below
  function showServerErrors(details) {
    const rest = [];
    for (const d of details) {
      const loc = d.loc || [];
      const pm = /^parameter (\w+)=/.exec(d.msg) || /parameter '(\w+)'/.exec(d.msg);
      if (loc.includes("max_fps")) fieldError("max_fps", d.msg);
      else if (loc.includes("gain") || /display gain/.test(d.msg)) fieldError("gain", d.msg);
      else if (pm && $("param-" + pm[1])) fieldError("param-" + pm[1], d.msg.replace(/^parameter \w+=\S+: /, ""));
      else rest.push(d.msg);
    }
    return rest;
  }

  // ---- applying: changes go to the service as the user makes them (debounced) -----------------
  const DEBOUNCE_MS = 400;
  let applyTimer = null, applyPending = false, inFlight = false, again = false, lastApplyAt = 0;
  function scheduleApply(delay = DEBOUNCE_MS) {
    clearTimeout(applyTimer);
    applyPending = true;
    applyTimer = setTimeout(() => applyConfig(), delay);
  }
  async function applyConfig(body) {
    applyPending = false;
    if (inFlight) { again = true; return; }
    const method = $("method-select").value;
    if (!body) {
      if (!checkAll()) { msg($("config-msg"), "not sent: fix the marked field", true); return; }
      body = {
        method, params: readParams(),
        ...(readTier() ? { quality: readTier() } : {}),
        display: { gain_mode: $("gain-mode").value, gain: Number($("gain").value) || null },
        max_fps: Number($("max-fps").value),
      };
    }
    inFlight = true; lastApplyAt = performance.now();
    msg($("config-msg"), "applying...");
    try {
      const c = await api("/api/config", { method: "PUT", body });
      const rebuild = !state.config || state.config.method !== c.method || body.params === undefined;
      state.config = c; state.applied++;
      if (state.pinned) state.pinned.aligned = 0;  // a new config: its frames are aligned again
      if (rebuild) buildParams(c.method, c.params, c.quality);
      for (const el of document.querySelectorAll(".field-err")) el.textContent = "";
      for (const el of document.querySelectorAll(".invalid")) el.classList.remove("invalid");
      msg($("config-msg"), c.__status === 202 || c.state === "pending"
        ? "sent: " + c.method + " starts once the worker is ready (compiling)" : "applied: " + c.method);
    } catch (e) {
      const rest = showServerErrors(e.details || [{ loc: [], msg: e.message }]);
      msg($("config-msg"), rest.length ? rest.join("; ") : "not applied: see the marked field", true);
    } finally {
      inFlight = false; lastApplyAt = performance.now();
    }
    if (again) { again = false; scheduleApply(0); }
  }

  $("method-select").addEventListener("change", () => {
    clearTimeout(applyTimer);
    if (state.pinned) state.pinned.aligned = 0;
    const name = $("method-select").value;
    buildParams(name, null);
    // a new method starts from its defaults (the service resets them on a method change)
    applyConfig({ method: name });
  });
  $("preset-select").addEventListener("change", () => {
    const m = state.methods[$("method-select").value];
    const p = $("preset-select").value;
    if (!m || p === "custom") return;
    const vals = Object.assign(paramDefaults(m), p === "defaults" ? {} : m.presets[p]);
    buildParams(m.name, vals, readTier());
    scheduleApply(0);
  });
  $("quality-select").addEventListener("change", () => scheduleApply(0));
  for (const id of ["gain-mode", "gain", "max-fps"]) {
    $(id).addEventListener(id === "gain-mode" ? "change" : "input", () => { checkDisplay(); scheduleApply(); });
  }

  async function loadMethods() {
    const list = await api("/api/methods");
    const sel = $("method-select");
    sel.innerHTML = "";
    for (const m of list) {
      state.methods[m.name] = m;
      const o = document.createElement("option");
      o.value = m.name; o.textContent = m.name + (m.masks.length ? " (masks)" : "");
      o.title = m.summary;
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
    const ok = el.checkValidity();
    if (ok && $("record-msg").classList.contains("error")) msg($("record-msg"), "");
    return ok;
  }
  $("record-name").addEventListener("input", checkRecordName);

  async function loadConfig() {
    const c = await api("/api/config");
    state.config = c;
    $("method-select").value = c.method;
    buildParams(c.method, c.params, c.quality);
    $("gain-mode").value = c.display.gain_mode;
    if (c.display.gain) $("gain").value = c.display.gain;
    else if (c.effective_gain) $("gain").value = c.effective_gain;
    $("max-fps").value = c.max_fps;
  }

  // ---- compare: a pinned frame beside the live one, split by a slider ---------------------------
  function setSplit() {
    if (!state.pinned) return;
    const s = Number($("split").value);
    pinCanvas.style.clipPath = "inset(0 " + (100 - s) + "% 0 0)";
    $("split-line").style.left = "calc(" + s + "% - 1px)";
  }
  $("split").addEventListener("input", setSplit);
  function showCompareLabels() {
    const p = state.pinned;
    for (const id of ["label-a", "label-b", "split-line"]) $(id).classList.toggle("hidden", !p);
    if (!p || !latest) return;
    $("label-a").textContent = "pinned: " + p.frame.method + " @ step " + p.frame.step;
    $("label-b").textContent = "live: " + latest.method + " @ step " + latest.step;
    const d = latest.step - p.frame.step;
    const paused = replayState() && !replayState().playing;
    $("compare-msg").textContent = d === 0
      ? (latest.method === p.frame.method ? "same step, same method: pick another method or parameter"
        : "same step: " + p.frame.method + " (left) vs " + latest.method + " (right)")
      : "live frame is " + Math.abs(d) + " steps " + (d > 0 ? "later" : "earlier")
        + (paused ? (d < 0 ? " (this method looks further ahead: pin it first to compare on one step)" : "")
          : " (pause the replay to compare on one step)");
  }
  // On a paused replay each method outputs a step its own look-ahead before the same data end,
  // so the live frame may be earlier or later than the pinned one. Later: the service holds
  // the pinned step (holdAt). Earlier: deliver the difference, and it reaches the pinned step.
  let aligning = 0;
  async function alignCompare(f) {
    const p = state.pinned, r = replayState();
    const d = f.step - (p ? p.frame.step : f.step);
    // only after a config change since the pin, and once the chosen method is on the pinned
    // step, not again: the steps a user takes are theirs
    if (!p || !r || r.playing || aligning || p.aligned >= 3 || state.applied === p.appliedAt) return;
    if (!state.config || f.method !== state.config.method) return;  // the old config's frames
    if (d === 0) { p.aligned = 3; return; }
    aligning = 1; p.aligned = (p.aligned || 0) + 1;
    try {
      if (d < 0) noteReplay(await replay("POST", "/api/replay/step", { n: -d }));
    } finally { aligning = 0; }
  }
  async function startCompare() {
    const r = state.lastStatus && state.lastStatus.source && state.lastStatus.source.replay;
    // a replay is paused first, so both sides show the same step
    if (r && r.playing) { noteReplay(await replay("PUT", "/api/replay", { playing: false })); await nextFrame(); }
    if (!latest) await nextFrame();
    const f = latest;
    state.pinned = { frame: f, params: state.config ? state.config.params : {}, redraw: true, appliedAt: state.applied };
    if (replayState()) await holdAt(f.step);  // the next methods' frames on this step too
    state.compare = true;
    pinCanvas.classList.remove("hidden");
    $("compare-bar").classList.remove("hidden");
    $("compare").classList.add("active");
    fit(); dirty = true;
  }
  function stopCompare() {
    state.pinned = null; state.compare = false;
    if (held) holdAt(null);
    pinCanvas.classList.add("hidden");
    $("compare-bar").classList.add("hidden");
    $("compare").classList.remove("active");
    showCompareLabels();
  }
  $("compare").addEventListener("click", () => (state.pinned ? stopCompare() : startCompare()));
  $("compare-close").addEventListener("click", stopCompare);

  // ---- snapshot: PNG of the frame as shown, and its masks, with the settings inside -------------
  const CRC = new Uint32Array(256);
  for (let n = 0; n < 256; n++) { let c = n; for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1; CRC[n] = c >>> 0; }
  function crc32(bytes) { let c = 0xffffffff; for (const b of bytes) c = CRC[(c ^ b) & 0xff] ^ (c >>> 8); return (c ^ 0xffffffff) >>> 0; }
  // PNG tEXt chunks (keyword, Latin-1 text) after IHDR: any PNG reader shows them
  function withText(png, fields) {
    const enc = (s) => Uint8Array.from(s, (ch) => { const c = ch.charCodeAt(0); return c < 256 ? c : 63; });
    const chunks = [];
    for (const [k, v] of Object.entries(fields)) {
      const data = new Uint8Array([...enc(k), 0, ...enc(v)]);
      const out = new Uint8Array(12 + data.length), dv = new DataView(out.buffer);
      dv.setUint32(0, data.length);
      out.set(enc("tEXt"), 4); out.set(data, 8);
      dv.setUint32(8 + data.length, crc32(out.subarray(4, 8 + data.length)));
      chunks.push(out);
    }
    const head = 8 + 25;  // signature + IHDR
    const total = png.length + chunks.reduce((a, c) => a + c.length, 0);
    const out = new Uint8Array(total);
    out.set(png.subarray(0, head));
    let o = head;
    for (const c of chunks) { out.set(c, o); o += c.length; }
    out.set(png.subarray(head), o);
    return out;
  }
  function canvasPng(c) {
    return new Promise((resolve) => c.toBlob(async (b) => resolve(new Uint8Array(await b.arrayBuffer())), "image/png"));
  }
  function download(bytes, name) {
    const url = URL.createObjectURL(new Blob([bytes], { type: "image/png" }));
    const a = document.createElement("a");
    a.href = url; a.download = name;
    document.body.appendChild(a); a.click(); a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  }
  async function snapshot() {
    const f = latest;
    if (!f) return null;
    // the parameters that made this frame: its own tier, not the live mode ("auto")
    const chosen = state.config && state.config.method === f.method ? state.config.params : {};
    const params = f.quality ? Object.assign({}, chosen, { quality: f.quality }) : chosen;
    const fields = {
      Software: "CFSR live viewer", method: f.method, step: String(f.step),
      parameters: JSON.stringify(params), masks: Object.keys(f.masks).join(","),
      view: document.querySelector('input[name="view"]:checked').value
        + MASKS.filter((m) => f.masks[m.name] && maskBox(m.name).checked).map((m) => "+" + m.name).join(""),
      "display gain": f.gain.toFixed(4) + " spikes/step",
    };
    const base = "cfsr-" + f.method + "-step" + f.step;
    const names = [];
    download(withText(await canvasPng(canvas), fields), base + ".png");
    names.push(base + ".png");
    const planes = MASKS.map((m) => m.name).filter((nm) => f.masks[nm]).slice(0, 3);
    if (planes.length) {
      // masks as their own picture, one colour channel each (255 where set)
      const c = document.createElement("canvas"); c.width = f.w; c.height = f.h;
      const mctx = c.getContext("2d"), img = mctx.createImageData(f.w, f.h);
      for (let p = 0, o = 0; p < f.w * f.h; p++, o += 4) {
        planes.forEach((nm, ch) => { img.data[o + ch] = bit(f.masks[nm], p) ? 255 : 0; });
        img.data[o + 3] = 255;
      }
      mctx.putImageData(img, 0, 0);
      const channels = planes.map((nm, ch) => ["red", "green", "blue"][ch] + ": " + nm + " mask").join(", ");
      download(withText(await canvasPng(c), Object.assign({}, fields, { channels })), base + "-masks.png");
      names.push(base + "-masks.png");
    }
    state.lastSnapshot = { names, fields };
    return names;
  }
  $("snapshot").addEventListener("click", snapshot);

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
  const STEP_FRAMES = 256;
  let seeking = false;
  async function replay(method, path, body) {
    try { return await api(path, { method, body }); }
    catch (e) { msg($("replay-msg"), e.message, true); return null; }
  }
  const replayState = () => state.lastStatus && state.lastStatus.source && state.lastStatus.source.replay;
  // the replay's state as an answer just gave it (the status poll lags up to a second: a
  // replay just paused must not read as playing)
  function noteReplay(st) {
    if (st && state.lastStatus && state.lastStatus.source) state.lastStatus.source.replay = st;
  }
  // While comparing on a paused replay the service computes frames at the pinned step (a
  // method that looks less far ahead would show a later one); anything the user does to the
  // replay (play, a step, a seek) ends that, and the live side moves on.
  let held = false;
  async function holdAt(step) { held = step !== null; return replay("POST", "/api/replay/hold", { step }); }
  async function userReplay(method, path, body) {
    if (held) await holdAt(null);
    return replay(method, path, body);
  }
  function stepBack() {
    const r = replayState();
    if (r) userReplay("POST", "/api/replay/seek", { position: Math.max(r.start, r.position - 2 * STEP_FRAMES) })
      .then(() => replay("POST", "/api/replay/step", { n: STEP_FRAMES }));
  }
  $("play").addEventListener("click", () => userReplay("PUT", "/api/replay", { playing: true }));
  $("pause").addEventListener("click", () => replay("PUT", "/api/replay", { playing: false }));
  $("step").addEventListener("click", () => userReplay("POST", "/api/replay/step", { n: STEP_FRAMES }));
  $("back").addEventListener("click", stepBack);
  $("loop").addEventListener("change", () => replay("PUT", "/api/replay", { loop: $("loop").checked }));
  $("speed").addEventListener("change", () => replay("PUT", "/api/replay", { speed: Number($("speed").value) }));
  $("seek").addEventListener("input", () => { seeking = true; });
  $("seek").addEventListener("change", async () => {
    await userReplay("POST", "/api/replay/seek", { position: Number($("seek").value) });
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
    $("pause").classList.toggle("active", !r.playing);
    if (document.activeElement !== $("speed")) {
      const opt = [...$("speed").options].find((o) => Number(o.value) === r.speed);
      if (opt) $("speed").value = opt.value;
    }
    if (document.activeElement !== $("loop")) $("loop").checked = r.loop;
  }

  // ---- keyboard: space play/pause, arrows step, m masks, c compare ------------------------------------
  document.addEventListener("keydown", (ev) => {
    const t = ev.target;
    if (ev.ctrlKey || ev.metaKey || ev.altKey) return;
    if (t && (t.isContentEditable || ["INPUT", "SELECT", "TEXTAREA"].includes(t.tagName) && t.type !== "checkbox" && t.type !== "radio")) return;
    const r = replayState();
    if (ev.key === " ") {
      ev.preventDefault();
      if (r) userReplay("PUT", "/api/replay", { playing: !r.playing });
    } else if (ev.key === "ArrowRight") {
      ev.preventDefault();
      if (r) userReplay("POST", "/api/replay/step", { n: STEP_FRAMES });
    } else if (ev.key === "ArrowLeft") {
      ev.preventDefault();
      stepBack();
    } else if (ev.key === "m" || ev.key === "M") {
      const boxes = MASKS.map((m) => maskBox(m.name)).filter((b) => !b.disabled);
      const on = !boxes.some((b) => b.checked);
      for (const b of boxes) { b.checked = on; b.dispatchEvent(new Event("change")); }
    } else if (ev.key === "c" || ev.key === "C") {
      $("compare").click();
    }
  });

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
  function setDrop(id, v) {
    const el = $(id);
    el.textContent = big(v);
    el.parentElement.classList.toggle("nonzero", v > 0);
    el.parentElement.classList.toggle("hidden", v === undefined && (id === "drop-late" || id === "drop-order"));
  }
  function workerText(w) {
    let t = w.alive ? "alive" : "down";
    if (w.workers !== undefined && w.workers !== null) {
      t = w.workers + " process" + (w.workers === 1 ? "" : "es")
        + (w.threads_per_worker ? " x " + w.threads_per_worker + " thread" + (w.threads_per_worker === 1 ? "" : "s") : "")
        + ", " + t;
    }
    // frames below acquisition once the kernels are cached (compiles stay at the default)
    if (w.reconstruction_nice) t += ", frames at nice " + w.reconstruction_nice;
    return t + ", restarts " + w.restarts;
  }
  // the mode, the tier that made the frame on screen (the frame's own header, else the
  // status's), and the shares of the last 10 s under this config
  function qualityText(q, f) {
    const full = q.full || 0, fast = q.fast || 0, n = full + fast;
    const tier = (f && f.quality) || q.shown;
    const share = n ? Math.round(100 * full / n) + " % full, " + Math.round(100 * fast / n) + " % fast in 10 s" : "no frames yet";
    return (q.mode || "-") + (q.mode === "auto" && tier ? ": " + tier : "")
      + (q.mode === "auto" || n ? " (" + share + ")" : "");
  }
  // while a method compiles the service shows the ladder (TFP, then CSR for CFSR): say which
  // rung is shown and what the chosen method's first frame waits on, kernel by kernel
  function kernelText(c) {
    const of = c.total ? "/" + c.total : "";
    const est = c.estimate_s ? " of ~" + Math.round(c.estimate_s) : "";
    const name = c.kernel ? c.kernel.split(".").pop() : "";
    const what = name ? (c.waiting ? ", waiting for " : ", ") + name : "";
    return "kernel " + c.kernels + of + what + ", " + Math.round(c.cpu_s) + est + " CPU s";
  }
  function compileNote(s) {
    const w = s.worker, k = s.kernels, c = w.compiling;
    // the status may lag the frames by a poll: once frames of the chosen method arrive,
    // nothing is shown in its place any more
    const arrived = latest && latest.method === s.method;
    if (arrived) return k && k.state === "failed" ? "kernel warm-up failed: " + k.error : "";
    const progress = c ? kernelText(c) : "";
    const target = (c && c.method) || s.method;
    if (w.fallback_method) {
      return "showing " + w.fallback_method.toUpperCase() + " while " + target.toUpperCase()
        + " compiles" + (progress ? " (" + progress + ")" : "");
    }
    if (c) return "compiling " + target.toUpperCase() + " (" + progress + ")";
    if (k && k.state === "compiling") {
      return "compiling kernels in the background (" + k.ready.length + "/"
        + (k.ready.length + k.pending.length) + " methods" + (k.kernel ? "; " + k.kernel : "") + ")";
    }
    if (k && k.state === "failed") return "kernel warm-up failed: " + k.error;
    return "";
  }
  async function pollStatus() {
    try {
      const s = await api("/api/status");
      state.lastStatus = s; state.statusUpdates++;
      const w = s.worker;
      $("fig-input").textContent = big(s.input_steps_per_s);
      $("fig-rtf").textContent = fmt(s.real_time_factor, 3);
      $("fig-worker-rate").textContent = big(w.steps_per_s);
      $("fig-fps").textContent = fmt(s.output_fps, 1);
      // a paused replay's frames reuse old spikes: their age is no latency
      const paused = s.source.replay && !s.source.replay.playing;
      $("fig-latency").textContent = paused ? "paused" : fmt(s.latency_ms, 1);
      $("fig-latency-unit").classList.toggle("hidden", !!paused);
      $("fig-compute").textContent = fmt(s.compute_ms, 1);
      $("fig-worker").textContent = workerText(w);
      const hasQ = w.quality && w.quality.mode;
      $("fig-quality-box").classList.toggle("hidden", !hasQ);
      if (hasQ) $("fig-quality").textContent = qualityText(w.quality, latest && latest.method === s.method ? latest : null);
      const note = compileNote(s);
      $("compile-note").textContent = note;
      $("compile-note").classList.toggle("hidden", !note);
      setDrop("drop-usb", s.drops.usb); setDrop("drop-replay", s.drops.replay);
      setDrop("drop-ring", s.drops.ring); setDrop("drop-worker", s.drops.worker);
      setDrop("drop-late", w.dropped_late); setDrop("drop-order", w.dropped_order);
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
      // another tab (or the command line) changed the method: follow it, unless this page is
      // applying its own change right now
      const quiet = !inFlight && !applyPending && performance.now() - lastApplyAt > 3000;
      if (quiet && state.config && state.config.method !== s.method) await loadConfig();
      msg($("status-msg"), s.source.last_error ? "source: " + s.source.last_error : "");
    } catch (e) { msg($("status-msg"), "status: " + e.message, true); }
    setTimeout(pollStatus, 1000);
  }

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
    try { await loadSchema(); } catch (e) { msg($("config-msg"), "frame schema: " + e.message, true); return; }
    connect();
    try { await loadLimits(); await loadMethods(); await loadConfig(); await loadSources(); }
    catch (e) { msg($("config-msg"), e.message, true); }
    pollStatus();
  })();
})();
