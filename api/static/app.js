/* posecell dashboard: vanilla JS, no build step, nothing fetched from outside the cell PC.
 *
 * Data sources: GET /health every second (status bar, device cards), WS /ws/poses (live pose,
 * deviation, strip charts), GET /frames/latest about once a second (set-up image), POST /measure
 * (the button), GET /events and /measurements every few seconds (history).
 * Every failure is shown as its `reason` and `message`; the page never goes blank.
 * URLs are relative so the page also works behind a reverse proxy under a path prefix.
 */
"use strict";

(() => {
  const HEALTH_EVERY_MS = 1000;
  const FRAME_EVERY_MS = 1000;
  const HISTORY_EVERY_MS = 5000;
  const CHART_WINDOW_MS = 60000;
  const STALE_AFTER_MS = 3000;
  const WS_RATE_HZ = 10;
  const WS_BACKOFF_MS = [500, 1000, 2000, 4000, 8000, 10000];
  const TOKEN_KEY = "posecell.token";

  const $ = (id) => document.getElementById(id);

  // ---------------------------------------------------------------------------------------------
  // small helpers

  /** Build an element; children may be strings (always inserted as text, never as HTML). */
  function el(tag, props, ...children) {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(props || {})) {
      if (v === undefined || v === null || v === false) continue;
      if (k === "class") node.className = v;
      else if (k === "text") node.textContent = v;
      else node.setAttribute(k, v === true ? "" : String(v));
    }
    for (const c of children) {
      if (c === null || c === undefined) continue;
      node.append(c instanceof Node ? c : document.createTextNode(String(c)));
    }
    return node;
  }

  const isNum = (v) => typeof v === "number" && Number.isFinite(v);
  const fix = (v, digits) => (isNum(v) ? v.toFixed(digits) : "–");
  const signed = (v, digits) => (isNum(v) ? (v >= 0 ? "+" : "−") + Math.abs(v).toFixed(digits) : "–");
  const pad = (n, w = 2) => String(n).padStart(w, "0");

  function fmtTime(iso) {
    if (!iso) return "–";
    const d = new Date(iso);
    if (Number.isNaN(d.getTime())) return String(iso);
    const t = `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
    const today = new Date();
    if (d.toDateString() === today.toDateString()) return t;
    return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${t}`;
  }

  function fmtDuration(s) {
    if (!isNum(s)) return "–";
    s = Math.floor(s);
    const d = Math.floor(s / 86400), h = Math.floor((s % 86400) / 3600);
    const m = Math.floor((s % 3600) / 60), sec = s % 60;
    if (d > 0) return `${d} d ${h} h`;
    if (h > 0) return `${h} h ${pad(m)} min`;
    if (m > 0) return `${m} min ${pad(sec)} s`;
    return `${sec} s`;
  }

  const position = (T) => (Array.isArray(T) && T.length >= 3 ? [T[0][3], T[1][3], T[2][3]] : null);
  const triple = (v, digits, unit) =>
    Array.isArray(v) ? v.map((x) => fix(x, digits)).join(", ") + (unit ? ` ${unit}` : "") : "–";
  const signedTriple = (v, digits, unit) =>
    Array.isArray(v) ? v.map((x) => signed(x, digits)).join(", ") + (unit ? ` ${unit}` : "") : "–";

  /** A failure block: the reason code in bold mono, then the sentence. */
  function failureContent(reason, message, extra) {
    return [
      el("span", { class: "reason", text: reason || "error" }),
      el("span", { text: message || "no message was given" }),
      extra ? el("span", { class: "muted", text: ` (${extra})` }) : null,
    ].filter(Boolean);
  }

  function showFailure(node, reason, message, extra, warn) {
    node.replaceChildren(...failureContent(reason, message, extra));
    node.classList.toggle("warn", Boolean(warn));
    node.hidden = false;
  }

  /** A reason/message pair for a response that was not what we hoped for. */
  function problemOf(status, data, text) {
    if (data && typeof data === "object" && data.reason) {
      return { reason: String(data.reason), message: String(data.message || "") || `HTTP ${status}` };
    }
    const snippet = (text || "").trim().slice(0, 200);
    return { reason: `http_${status}`, message: snippet || `the service answered HTTP ${status}` };
  }

  /** fetch with a timeout; resolves {status, ok, data, text} or throws {reason, message}. */
  async function request(url, { method = "GET", headers = {}, body, timeoutMs = 5000, as = "json" } = {}) {
    const ctl = new AbortController();
    const timer = setTimeout(() => ctl.abort(), timeoutMs);
    let res;
    try {
      res = await fetch(url, { method, headers, body, cache: "no-store", signal: ctl.signal });
    } catch (e) {
      clearTimeout(timer);
      if (e && e.name === "AbortError") {
        throw { reason: "timeout", message: `no answer from the service within ${timeoutMs / 1000} s (${url})` };
      }
      throw { reason: "network_error", message: `the service at ${location.host} does not answer (${e && e.message})` };
    }
    try {
      if (as === "blob" && res.ok) return { status: res.status, ok: true, blob: await res.blob() };
      const text = await res.text();
      let data = null;
      try { data = text ? JSON.parse(text) : null; } catch (_) { data = null; }
      return { status: res.status, ok: res.ok, data, text };
    } catch (e) {
      throw { reason: "network_error", message: `the answer from ${url} was cut off (${e && e.message})` };
    } finally {
      clearTimeout(timer);
    }
  }

  const asProblem = (e) =>
    e && e.reason ? e : { reason: "dashboard_error", message: String((e && e.message) || e) };

  // ---------------------------------------------------------------------------------------------
  // state

  const state = {
    health: null,
    selected: "", // "" = the newest result of any camera
    latest: new Map(), // camera -> newest result
    lastOk: new Map(), // camera -> newest ok result
    received: new Map(), // camera -> Date.now() of the newest result
    series: [], // {t, camera, ok, dev, lat}
    shown: null, // the result on screen
  };

  const banner = {
    sources: new Map(),
    set(source, problem) {
      if (problem) this.sources.set(source, problem);
      else this.sources.delete(source);
      const node = $("banner");
      if (!this.sources.size) { node.hidden = true; node.replaceChildren(); return; }
      node.replaceChildren(...[...this.sources.values()].map((p) => el("div", {}, ...failureContent(p.reason, p.message))));
      node.hidden = false;
    },
  };

  // ---------------------------------------------------------------------------------------------
  // health: status bar and device cards

  function setPill(node, stateName, text) {
    node.dataset.state = stateName;
    node.textContent = text;
  }

  async function pollHealth() {
    try {
      const r = await request("health", { timeoutMs: 4000 });
      if (!r.ok || !r.data || typeof r.data.status !== "string") {
        const p = problemOf(r.status, r.data, r.text);
        throw p;
      }
      state.health = r.data;
      state.healthAt = Date.now();
      renderHealth(r.data);
      banner.set("health", null);
      document.body.classList.remove("health-stale");
      $("devices-note").hidden = true;
    } catch (e) {
      const p = asProblem(e);
      setPill($("status"), "unreachable", "unreachable");
      banner.set("health", p);
      // what is still on screen is the last known state, not the present one: say so
      document.body.classList.add("health-stale");
      const note = $("devices-note");
      note.textContent = state.healthAt
        ? `Last known states, from ${fmtTime(new Date(state.healthAt).toISOString())}: the service does not answer.`
        : "The service has not answered yet.";
      note.hidden = false;
    } finally {
      setTimeout(pollHealth, HEALTH_EVERY_MS);
    }
  }

  function renderHealth(h) {
    setPill($("status"), h.status, h.status);
    $("uptime").textContent = fmtDuration(h.uptime_s);
    const cams = Object.entries(h.cameras || {});
    $("fps").textContent = cams.length === 0 ? "no camera"
      : cams.length === 1 ? `${fix(cams[0][1].fps, 1)} fps`
      : cams.map(([n, c]) => `${n} ${fix(c.fps, 1)}`).join(" · ");
    const p = h.processing || {};
    $("latency").textContent = isNum(p.latency_ms_median)
      ? `${fix(p.latency_ms_median, 1)} ms` + (isNum(p.processing_ms_median) ? ` (proc. ${fix(p.processing_ms_median, 1)})` : "")
      : "–";
    $("results").textContent = isNum(p.ok) ? `${p.ok} / ${p.failed}` : "–";
    const ws = h.websocket || {};
    $("ws-drops").textContent = isNum(ws.dropped_total) ? String(ws.dropped_total) : "–";
    $("ws-drops").title = `messages dropped for slow clients since start; ${ws.clients ?? "?"} client(s) connected`;
    renderCameraSelect(cams.map(([n]) => n));
    renderCameras(cams, p.time_offset || {}, p.measurement || {});
    renderRobot(h.robot || {});
    renderCalibration(h.calibration || {});
  }

  function renderCameraSelect(names) {
    const sel = $("camera-select");
    const have = [...sel.options].map((o) => o.value).filter(Boolean);
    if (have.join("\n") === names.join("\n")) return;
    const keep = sel.value;
    sel.replaceChildren(el("option", { value: "", text: "newest of all" }),
      ...names.map((n) => el("option", { value: n, text: n })));
    sel.value = names.includes(keep) ? keep : "";
    sel.parentElement.hidden = names.length < 2;
  }

  const cameraCards = new Map();

  function renderCameras(cams, offsets, measurement) {
    const box = $("camera-cards");
    for (const [name, c] of cams) {
      let card = cameraCards.get(name);
      if (!card) {
        // the sensor's hot pixels mapped from dark frames by the service, its dead ones from frames of a
        // white card before the lens (POST /calibration/camera/defects)
        const mapButton = el("button", { type: "button", class: "ghost defects-map", text: "Map hot pixels",
          title: "8 frames with the ring light off (they give no pose), then the hot pixels found in them are " +
                 "saved and patched in every frame; uses the API token of “Triggered measurement”" });
        const deadButton = el("button", { type: "button", class: "ghost defects-dead", text: "Map dead pixels",
          title: "Hold a white card before the lens, lit evenly by the ring light, then press: 8 frames of it, " +
                 "the dead pixels found in them saved beside the hot ones and patched in every frame; uses the " +
                 "API token of “Triggered measurement”" });
        card = el("div", { class: "device camera", "data-camera": name },
          el("div", { class: "device-head" },
            el("span", { class: "device-name", text: `Camera ${name}` }), el("span", { class: "pill state" })),
          el("div", { class: "device-facts" }),
          el("p", { class: "device-error" }),
          el("div", { class: "device-actions" }, mapButton, deadButton,
            el("span", { class: "device-note", role: "status" })));
        mapButton.addEventListener("click", () => mapDefects(name, card, "hot"));
        deadButton.addEventListener("click", () => mapDefects(name, card, "dead"));
        cameraCards.set(name, card);
        box.append(card);
      }
      card.dataset.state = c.state;
      setPill(card.querySelector(".state"), c.state, c.state);
      const facts = [];
      if (isNum(c.fps)) facts.push(`${fix(c.fps, 1)} fps`);
      if (isNum(c.frames)) facts.push(`${c.frames} frames`);
      if (isNum(c.dropped)) facts.push(`${c.dropped} dropped`);
      if (isNum(c.disconnects) && c.disconnects > 0) facts.push(`${c.disconnects} disconnects`);
      if (isNum(c.last_frame_age_s)) facts.push(`last frame ${fix(c.last_frame_age_s, 1)} s ago`);
      if (c.trigger) facts.push(`trigger ${c.trigger}`);
      if (isNum(c.exposure_us)) {
        facts.push(`exposure ${fix(c.exposure_us, 0)} µs${c.auto_exposure && c.auto_exposure.on ? " (auto)" : ""}`);
      }
      // clipped disks are measured, but they say the exposure is too long (the sentence: on hover)
      if (isNum(c.targets_saturated) && c.targets_saturated > 0) facts.push(`${c.targets_saturated} targets saturated`);
      // how sharp the targets are; beyond 1.5 px the focus sentence says what to check (on hover too)
      if (isNum(c.blur_px) && c.blur_px > 0) facts.push(`blur ${fix(c.blur_px, 2)} px${c.focus ? " (out of focus)" : ""}`);
      // the sensor's hot pixels patched in each frame (POST /calibration/camera/defects, [[cameras]] defects)
      const defects = (measurement[name] || {}).defects;
      if (defects && isNum(defects.pixels)) {
        facts.push(`${defects.pixels} defect pixels patched` + (defects.dead > 0 ? ` (${defects.dead} dead)` : ""));
      }
      const off = offsets[name];
      if (off && isNum(off.offset_ms)) facts.push(`clock offset ${fix(off.offset_ms, 2)} ± ${fix(off.sigma_ms, 2)} ms`);
      card.querySelector(".device-facts").textContent = facts.join(" · ");
      card.querySelector(".device-facts").title = [c.saturation, c.focus].filter(Boolean).join("; ");
      // a device that is not ok always says why, even when the driver gave no sentence
      const error = c.error || (c.state !== "ok" ? `camera ${name} is ${c.state}` : "");
      card.querySelector(".device-error").textContent = error;
    }
    for (const [name, card] of cameraCards) {
      if (!cams.some(([n]) => n === name)) { card.remove(); cameraCards.delete(name); }
    }
  }

  async function mapDefects(name, card, kind) {
    const buttons = card.querySelectorAll(".defects-map, .defects-dead"), note = card.querySelector(".device-note");
    buttons.forEach((b) => { b.disabled = true; });
    note.dataset.state = "busy";
    note.textContent = kind === "hot" ? "taking dark frames…" : "taking frames of the card…";
    try {
      const r = await window.posecell.call("/calibration/camera/defects", {
        method: "POST", headers: window.posecell.headers(), body: JSON.stringify({ camera: name, kind }) });
      const what = kind === "hot" ? `${r.found} defect pixels mapped from ${r.frames} dark frames`
                                  : `${r.found} dead pixels mapped from ${r.frames} frames of the card`;
      const said = [what + (r.kept ? ` (${r.defects} in the map, the ${r.kept} ${kind === "hot" ? "dead" : "hot"} ` +
                                    "ones kept)" : "") + (r.applied ? ", patched from now on" : ", not in use")];
      if (r.warning) said.push(r.warning);
      if (!r.strobe_restored) said.push("the ring light's strobe could not be switched on again: see the events");
      note.dataset.state = r.warning || !r.strobe_restored ? "warn" : "ok";
      note.textContent = said.join(" — ");
    } catch (e) {
      note.dataset.state = "failed";
      note.textContent = `${e.reason}: ${e.message}` +
        (e.status === 401 ? " (enter the API token under “Triggered measurement”)" : "");
    } finally {
      buttons.forEach((b) => { b.disabled = false; });
    }
  }

  function renderRobot(r) {
    const card = $("robot-card");
    card.dataset.state = r.state || "unknown";
    setPill(card.querySelector(".state"), r.state || "unknown", r.state || "unknown");
    const facts = [];
    if (r.driver) facts.push(`driver ${r.driver}`);
    if (isNum(r.rate_hz)) facts.push(`${fix(r.rate_hz, 0)} Hz`);
    if (r.moved_by) facts.push(`moved by ${r.moved_by}`);  // the one workflow moving the simulated arm
    card.querySelector(".device-facts").textContent = facts.join(" · ");
    const error = r.error || (r.state && !["ok", "absent"].includes(r.state) ? `the robot is ${r.state}` : "");
    card.querySelector(".device-error").textContent = r.state === "absent" ? "no robot is configured" : error;
  }

  const CALIB_LABELS = { camera: "Camera (interior)", field: "Field (targets)", handeye: "Hand-eye",
                         rig: "Rig (relative orientation)", robot: "Robot model (kinematics)" };
  // not needed to measure: without one the controller's nominal model stands
  const OPTIONAL_CALIB = { robot: "none: the nominal model (the robot calibration session makes one)" };

  function renderCalibration(cal) {
    // a rig calibration matters only with two or more cameras
    const nCameras = document.querySelectorAll(".device.camera[data-camera]").length;
    const entries = Object.entries(cal).filter(([kind, c]) => kind !== "rig" || nCameras > 1 || (c && c.present));
    const rows = entries.map(([kind, c]) => {
      const missing = !c || !c.present;
      const optional = missing && kind in OPTIONAL_CALIB;
      return el("tr", { class: optional ? "optional" : missing ? "missing" : null, "data-kind": kind },
        el("td", { text: CALIB_LABELS[kind] || kind }),
        el("td", { text: optional ? "–" : missing ? "missing" : `v${c.version}` }),
        el("td", { text: optional ? OPTIONAL_CALIB[kind]
                         : missing ? `not loaded: upload it (PUT /calibration/${kind})` : c.source || "–" }));
    });
    $("calibration").tBodies[0].replaceChildren(...rows);
  }

  // ---------------------------------------------------------------------------------------------
  // live stream

  const ws = { sock: null, attempt: 0, retryAt: 0, timer: null, everOpen: false };

  function wsUrl() {
    const u = new URL(`ws/poses?max_rate_hz=${WS_RATE_HZ}`, location.href);
    u.protocol = location.protocol === "https:" ? "wss:" : "ws:";
    return u.href;
  }

  function connectStream() {
    clearTimeout(ws.timer);
    let sock;
    try {
      sock = new WebSocket(wsUrl());
    } catch (e) {
      scheduleReconnect(`cannot open the stream: ${e && e.message}`);
      return;
    }
    ws.sock = sock;
    setPill($("ws-state"), "starting", "connecting…");
    sock.onopen = () => {
      ws.attempt = 0;
      ws.everOpen = true;
      setPill($("ws-state"), "live", "live");
      banner.set("stream", null);
    };
    sock.onmessage = (ev) => {
      let r;
      try { r = JSON.parse(ev.data); } catch (_) { return; }
      if (r && typeof r === "object") onResult(r);
    };
    sock.onclose = (ev) => {
      if (ws.sock !== sock) return;
      ws.sock = null;
      const why = ev.code === 1000 || ev.code === 1001 ? "the service closed the stream"
        : ev.code === 1012 ? "the service is restarting"
        : ev.code === 1006 ? "the connection to the service was lost" : `the stream closed with code ${ev.code}`;
      scheduleReconnect(why);
    };
    sock.onerror = () => { /* a close event follows and schedules the retry */ };
  }

  function scheduleReconnect(why) {
    const base = WS_BACKOFF_MS[Math.min(ws.attempt, WS_BACKOFF_MS.length - 1)];
    const delay = Math.round(base * (0.8 + 0.4 * Math.random())); // jitter: many tablets must not retry in step
    ws.attempt += 1;
    ws.retryAt = Date.now() + delay;
    ws.why = why;
    updateStreamPill();
    banner.set("stream", { reason: "stream_disconnected", message: `${why}; retrying with backoff` });
    ws.timer = setTimeout(connectStream, delay);
  }

  function updateStreamPill() {
    if (ws.sock) return;
    const s = Math.max(0, (ws.retryAt - Date.now()) / 1000);
    setPill($("ws-state"), "disconnected", `disconnected · retry in ${s.toFixed(0)} s`);
  }

  function onResult(r) {
    const cam = r.camera || "";
    const now = Date.now();
    state.latest.set(cam, r);
    // the age shown is that of the newest measured frame: an outage result (no seq) says what is
    // wrong now but is no new measurement; a backfilled result comes with its age
    if (r.seq !== undefined && r.seq !== null) state.received.set(cam, now - (isNum(r.age_s) ? r.age_s * 1000 : 0));
    if (r.ok) state.lastOk.set(cam, r);
    state.series.push({
      t: now,
      camera: cam,
      ok: Boolean(r.ok),
      dev: r.deviation && isNum(r.deviation.position_mm) ? r.deviation.position_mm : null,
      lat: r.timings_ms && isNum(r.timings_ms.latency) ? r.timings_ms.latency : null,
    });
    while (state.series.length && state.series[0].t < now - CHART_WINDOW_MS - 2000) state.series.shift();
    if (!state.selected || state.selected === cam) renderResult(r);
    chartsDirty = true;
  }

  function selectedResult() {
    if (state.selected) return state.latest.get(state.selected) || null;
    let best = null;
    for (const r of state.latest.values()) if (!best || (r.t_exposure_host_ns || 0) > (best.t_exposure_host_ns || 0)) best = r;
    return best;
  }

  function renderResult(r) {
    state.shown = r;
    const cam = r.camera || "";
    const pose = $("pose");
    pose.dataset.seq = r.seq ?? "";
    pose.dataset.camera = cam;
    pose.dataset.ok = String(Boolean(r.ok));
    $("pose-meta").textContent = `${cam} · seq ${r.seq ?? "–"} · ${fmtTime(r.t_wall)}`;

    // on a failed frame, keep the last good values dimmed under the reason, so nothing jumps to blank
    const good = r.ok ? r : state.lastOk.get(cam);
    if (r.ok) $("pose-failure").hidden = true;
    else showFailure($("pose-failure"), r.reason, r.message, good ? `last good pose at ${fmtTime(good.t_wall)}` : null);
    pose.classList.toggle("failed", !r.ok);

    const p = good ? position(good.T_field_camera) : null;
    $("pose-x").textContent = p ? fix(p[0], 2) : "–";
    $("pose-y").textContent = p ? fix(p[1], 2) : "–";
    $("pose-z").textContent = p ? fix(p[2], 2) : "–";
    $("pose-sigma").textContent = good ? triple(good.sigma_position_mm, 3, "mm") : "–";
    $("pose-rms").textContent = good && isNum(good.rms_px) ? `${fix(good.rms_px, 3)} px` : "–";
    $("pose-targets").textContent = good ? `${good.n_coded ?? "–"} / ${good.n_uncoded ?? "–"}` : "–";
    const mode = r.mode || (good && good.mode);
    $("pose-mode").textContent = mode === "roi" ? "roi (tracking windows)" : mode === "full" ? "full (whole-frame search)" : mode || "–";
    const t = r.timings_ms || {};
    $("pose-timing").textContent = isNum(t.latency) ? `${fix(t.latency, 1)} ms / ${fix(t.processing, 1)} ms` : "–";

    renderDeviation(r, good);
  }

  function renderDeviation(r, good) {
    const src = r.ok ? r : good;
    const d = src && src.deviation;
    const box = $("deviation");
    box.dataset.ok = String(Boolean(d));
    $("dev-pos").textContent = d ? fix(d.position_mm, 3) : "–";
    $("dev-angle").textContent = d ? fix(d.angle_deg, 4) : "–";
    $("dev-vector").textContent = d ? signedTriple(d.vector_mm, 3, "mm") : "–";
    const pf = src ? position(src.T_base_flange) : null;
    $("dev-flange").textContent = pf ? triple(pf, 2, "mm") : "–";
    const missing = $("dev-missing");
    if (!r.ok) showFailure(missing, r.reason, "no pose in this frame, so no deviation", null, true);
    else if (!r.deviation) {
      showFailure(missing, r.flange_reason || "no_deviation",
        r.flange_message || "the result carries no flange deviation", null, true);
    } else missing.hidden = true;
    box.classList.toggle("stale", !r.ok || !r.deviation);
  }

  function tickAge() {
    updateStreamPill();
    const r = state.shown;
    const node = $("pose-age");
    if (!r) {
      node.textContent = ws.sock ? "waiting for the first result…" : "no stream";
      return;
    }
    const age = Date.now() - (state.received.get(r.camera || "") || 0);
    const stale = age > STALE_AFTER_MS;
    node.textContent = stale ? `${fix(age / 1000, 1)} s — no new result (see the camera's state)` : `${fix(age / 1000, 1)} s`;
    $("pose").classList.toggle("stale", stale);
    $("deviation").classList.toggle("stale", stale || !r.ok || !r.deviation);
  }

  // ---------------------------------------------------------------------------------------------
  // strip charts

  let chartsDirty = true;

  function niceCeil(v) {
    if (!(v > 0)) return 1;
    const e = Math.pow(10, Math.floor(Math.log10(v)));
    for (const m of [1, 2, 2.5, 5, 10]) if (v <= m * e) return m * e;
    return 10 * e;
  }

  function drawChart(canvas, key, color, unit, digits) {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(100, canvas.clientWidth), h = Math.max(60, canvas.clientHeight);
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    const g = canvas.getContext("2d");
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.clearRect(0, 0, w, h);
    const now = Date.now(), t0 = now - CHART_WINDOW_MS;
    const pts = state.series.filter((p) => p.t >= t0 && (!state.selected || p.camera === state.selected));
    const vals = pts.map((p) => p[key]).filter(isNum);
    // scale to the bulk of the data: one slow frame (a warm-up, a hiccup) must not flatten the rest;
    // values above the scale are drawn clipped at the top with a red cap
    const sorted = [...vals].sort((a, b) => a - b);
    const q = (f) => sorted[Math.min(sorted.length - 1, Math.floor(f * sorted.length))];
    const top = niceCeil(sorted.length ? Math.min(sorted[sorted.length - 1], 3 * q(0.9)) * 1.1 : 1);
    const L = 44, R = 8, T = 6, B = 18;
    const x = (t) => L + ((t - t0) / CHART_WINDOW_MS) * (w - L - R);
    const y = (v) => T + (1 - Math.min(v, top) / top) * (h - T - B);
    g.font = "11px system-ui, sans-serif";
    g.fillStyle = "#667085";
    g.strokeStyle = "#e4e8ee";
    g.lineWidth = 1;
    g.textBaseline = "middle";
    g.textAlign = "right";
    // grid lines at round values: the smallest 1/2/2.5/5 step that gives at most five intervals
    const step = niceCeil(top / 5);
    const stepDigits = (String(+step.toPrecision(3)).split(".")[1] || "").length;
    for (let i = 0; i * step <= top * 1.0001; i++) {
      const v = i * step;
      g.beginPath(); g.moveTo(L, Math.round(y(v)) + 0.5); g.lineTo(w - R, Math.round(y(v)) + 0.5); g.stroke();
      g.fillText(v.toFixed(stepDigits), L - 5, y(v));
    }
    g.textAlign = "center";
    g.textBaseline = "alphabetic";
    for (const s of [60, 45, 30, 15, 0]) g.fillText(s ? `−${s} s` : "now", x(now - s * 1000), h - 4);
    // the line breaks on a failed frame or a gap, so a missing stretch is never drawn as data
    g.strokeStyle = color;
    g.lineWidth = 1.6;
    g.beginPath();
    let prev = null;
    for (const p of pts) {
      const v = p[key];
      if (!isNum(v)) { prev = null; continue; }
      if (prev && p.t - prev.t < 1500) g.lineTo(x(p.t), y(v));
      else g.moveTo(x(p.t), y(v));
      prev = p;
    }
    g.stroke();
    g.fillStyle = "#c62828";
    for (const p of pts) {
      if (!p.ok) g.fillRect(x(p.t) - 1, h - B - 5, 2, 5);
      else if (isNum(p[key]) && p[key] > top) g.fillRect(x(p.t) - 2, T, 4, 3);
    }
    if (!pts.length) {
      g.fillStyle = "#98a2b3";
      g.textAlign = "center";
      g.fillText("no results in the last 60 s", (L + w - R) / 2, h / 2);
    }
    const last = vals.length ? vals[vals.length - 1] : null;
    return last === null ? "" : `now ${last.toFixed(digits)} ${unit}`;
  }

  function drawCharts() {
    $("chart-dev-now").textContent = drawChart($("chart-dev"), "dev", "#1f5fbf", "mm", 3);
    $("chart-lat-now").textContent = drawChart($("chart-lat"), "lat", "#8a4fbf", "ms", 1);
    chartsDirty = false;
  }

  // the time axis moves even without data, so redraw at 4 Hz; skip work while the tab is hidden
  function chartLoop() {
    if (!document.hidden) drawCharts();
    setTimeout(() => requestAnimationFrame(chartLoop), chartsDirty ? 250 : 500);
  }

  // ---------------------------------------------------------------------------------------------
  // latest frame

  let frameUrl = null;

  async function refreshFrame() {
    const started = Date.now();
    try {
      if ($("frame-live").checked && !document.hidden) await loadFrame();
    } finally {
      setTimeout(refreshFrame, Math.max(100, FRAME_EVERY_MS - (Date.now() - started)));
    }
  }

  async function loadFrame() {
    const which = state.selected ? `&camera=${encodeURIComponent(state.selected)}` : "";
    const img = $("frame-img");
    try {
      const r = await request(`frames/latest?format=jpeg&max_width=800${which}`, { as: "blob", timeoutMs: 5000 });
      if (!r.ok) throw problemOf(r.status, r.data, r.text);
      const url = URL.createObjectURL(r.blob);
      await new Promise((resolve, reject) => {
        img.onload = resolve;
        img.onerror = () => reject({ reason: "bad_image", message: "the frame could not be decoded by the browser" });
        img.src = url;
      });
      if (frameUrl) URL.revokeObjectURL(frameUrl);
      frameUrl = url;
      $("frame-meta").textContent =
        `${state.selected || "newest camera"} · ${img.naturalWidth}×${img.naturalHeight} · fetched ${fmtTime(new Date().toISOString())}`;
      // the service keeps serving the last frame of a camera that went away: say that it is old
      const cams = (state.health && state.health.cameras) || {};
      const name = state.selected || Object.keys(cams)[0];
      const cam = cams[name];
      if (cam && cam.state !== "ok") {
        img.classList.add("stale");
        showFailure($("frame-failure"), cam.state === "disconnected" ? "camera_disconnected" : `camera_${cam.state}`,
          `this is the last frame camera ${name} delivered${cam.error ? `; ${cam.error}` : ""}`, null, true);
      } else {
        img.classList.remove("stale");
        $("frame-failure").hidden = true;
      }
    } catch (e) {
      const p = asProblem(e);
      img.classList.add("stale");
      showFailure($("frame-failure"), p.reason, p.message);
    }
  }

  // ---------------------------------------------------------------------------------------------
  // triggered measurement

  function loadToken() {
    try { return localStorage.getItem(TOKEN_KEY) || ""; } catch (_) { return ""; }
  }

  function saveToken(v) {
    try {
      if (v) localStorage.setItem(TOKEN_KEY, v);
      else localStorage.removeItem(TOKEN_KEY);
    } catch (_) { /* private mode: the token only lives in the field */ }
  }

  async function measureNow() {
    const btn = $("measure-btn");
    const out = $("measure-result");
    const token = $("token").value.trim();
    btn.disabled = true;
    btn.textContent = "Measuring…";
    out.dataset.state = "busy";
    out.replaceChildren(el("p", { class: "muted", text: "Waiting for the next frame…" }));
    const headers = { "Content-Type": "application/json" };
    if (token) headers.Authorization = `Bearer ${token}`;
    const body = JSON.stringify(state.selected ? { camera: state.selected } : {});
    const t0 = performance.now();
    try {
      const r = await request("measure", { method: "POST", headers, body, timeoutMs: 10000 });
      const ms = performance.now() - t0;
      if (r.data && r.data.ok === true) renderMeasured(r.data, ms);
      else {
        const p = problemOf(r.status, r.data, r.text);
        renderMeasureFailure(p, `HTTP ${r.status}`, r.status === 401 && !token ? "enter the API token above" : null);
      }
    } catch (e) {
      renderMeasureFailure(asProblem(e), null, null);
    } finally {
      btn.disabled = false;
      btn.textContent = "Measure now";
      pollHistory();
    }
  }

  function renderMeasureFailure(p, extra, hint) {
    const out = $("measure-result");
    out.dataset.state = "failed";
    out.dataset.reason = p.reason;
    const box = el("div", { class: "failure" }, ...failureContent(p.reason, p.message, extra));
    out.replaceChildren(box, hint ? el("p", { class: "caption", text: hint }) : null);
  }

  function renderMeasured(m, ms) {
    const out = $("measure-result");
    out.dataset.state = "ok";
    out.dataset.reason = "";
    const d = m.deviation;
    const pc = position(m.T_field_camera);
    const pf = position(m.T_base_flange_measured);
    const rows = [
      ["Deviation", d ? `${fix(d.position_mm, 3)} mm · ${fix(d.angle_deg, 4)} deg` : "–"],
      ["Deviation vector", d ? signedTriple(d.vector_mm, 3, "mm") : "–"],
      ["Flange (measured)", pf ? triple(pf, 2, "mm") : "–"],
      ["Camera in field", pc ? triple(pc, 2, "mm") : "–"],
      ["σ position", triple(m.sigma_position_mm, 3, "mm")],
      ["rms / targets", `${fix(m.rms_px, 3)} px · ${m.n_coded ?? "–"} coded + ${m.n_uncoded ?? "–"} uncoded`],
      ["Camera · seq · mode", `${m.camera ?? "–"} · ${m.seq ?? "–"} · ${m.mode ?? "–"}`],
      ["Exposed", fmtTime(m.t_wall)],
      ["Round trip", `${fix(ms, 0)} ms`],
    ];
    const dl = el("dl", { class: "facts" });
    for (const [k, v] of rows) dl.append(el("dt", { text: k }), el("dd", { text: v }));
    const nodes = [el("p", { class: "headline", text: d ? `ok — deviation ${fix(d.position_mm, 3)} mm` : "ok — pose measured" }), dl];
    if (!d) {
      nodes.push(el("div", { class: "failure warn" }, ...failureContent(m.flange_reason || "no_deviation",
        m.flange_message || "the result carries no flange deviation")));
    }
    out.replaceChildren(...nodes);
  }

  // ---------------------------------------------------------------------------------------------
  // history

  let historyTimer = null;

  async function pollHistory() {
    clearTimeout(historyTimer);
    try {
      const [ev, ms] = await Promise.all([
        request("events?limit=20", { timeoutMs: 5000 }),
        request("measurements?limit=20", { timeoutMs: 5000 }),
      ]);
      for (const r of [ev, ms]) if (!r.ok) throw problemOf(r.status, r.data, r.text);
      renderEvents(ev.data.events || []);
      renderMeasurements(ms.data.measurements || []);
      $("history-failure").hidden = true;
    } catch (e) {
      const p = asProblem(e);
      showFailure($("history-failure"), p.reason, p.message);
    } finally {
      historyTimer = setTimeout(pollHistory, HISTORY_EVERY_MS);
    }
  }

  function renderEvents(events) {
    const rows = events.map((e) => el("tr", { "data-kind": e.kind },
      el("td", { text: fmtTime(e.t_wall) }),
      el("td", { class: `level level-${e.level}`, text: e.level || "" }),
      el("td", { text: e.kind || "" }),
      el("td", { text: e.message || "" })));
    if (!rows.length) rows.push(el("tr", {}, el("td", { colspan: 4, class: "muted", text: "no events yet" })));
    $("events").tBodies[0].replaceChildren(...rows);
  }

  function renderMeasurements(list) {
    const rows = list.map((m) => el("tr", {},
      el("td", { text: fmtTime(m.t_wall) }),
      el("td", { text: m.camera || "" }),
      m.ok ? el("td", { class: "good", text: "ok" }) : el("td", { class: "bad", text: m.reason || "failed" }),
      el("td", { class: "num", text: fix(m.deviation_position_mm, 3) }),
      el("td", { class: "num", text: fix(m.deviation_angle_deg, 4) }),
      el("td", { class: "num", text: fix(m.rms_px, 3) }),
      el("td", { class: "num", text: m.n_targets ?? "–" })));
    if (!rows.length) rows.push(el("tr", {}, el("td", { colspan: 7, class: "muted", text: "no stored measurements yet" })));
    $("measurements").tBodies[0].replaceChildren(...rows);
  }

  // ---------------------------------------------------------------------------------------------
  // wiring

  function init() {
    const token = $("token");
    token.value = loadToken();
    token.addEventListener("input", () => saveToken(token.value.trim()));
    $("token-show").addEventListener("click", (e) => {
      const show = token.type === "password";
      token.type = show ? "text" : "password";
      e.currentTarget.textContent = show ? "hide" : "show";
      e.currentTarget.setAttribute("aria-pressed", String(show));
    });
    $("measure-btn").addEventListener("click", measureNow);
    $("camera-select").addEventListener("change", (e) => {
      state.selected = e.target.value;
      const r = selectedResult();
      if (r) renderResult(r);
      chartsDirty = true;
      loadFrame();
    });
    for (const tab of document.querySelectorAll(".tab")) {
      tab.addEventListener("click", () => {
        for (const t of document.querySelectorAll(".tab")) t.setAttribute("aria-selected", String(t === tab));
        for (const p of document.querySelectorAll("[data-panel]")) p.hidden = p.dataset.panel !== tab.dataset.tab;
      });
    }
    window.addEventListener("error", (e) => banner.set("page", { reason: "dashboard_error", message: e.message }));
    $("camera-select").parentElement.hidden = true;

    pollHealth();
    connectStream();
    refreshFrame();
    pollHistory();
    setInterval(tickAge, 250);
    chartLoop();
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
