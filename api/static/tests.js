/* posecell dashboard: the accuracy tests panel (vanilla JS, beside app.js, nothing from outside).
 *
 * GET /tests every second while a test runs (every 5 s otherwise) fills the list and the progress
 * bar; POST /tests/{kind} starts one (with the parameters typed as JSON), POST /tests/{id}/stop
 * finishes a recording or cancels a program; a finished test's HTML report (GET /tests/{id}/report,
 * polar plot and tables) is shown in a frame of this page. The API token is the one typed into the
 * "Triggered measurement" card (kept in this browser's localStorage by app.js); the calls are cards.js's.
 * Every failure is shown as its `reason` and `message`.
 */
"use strict";

(() => {
  const FAST_MS = 1000;
  const SLOW_MS = 5000;
  const DEFAULTS = {
    circle: { program: { radius_mm: 150, speed_mm_s: 75, laps: 1 }, record: { radius_mm: 300 } },
    iso9283: { program: { cycles: 30 }, record: { frames_per_stop: 3 } },
    table1: { program: { positions: 6 }, record: { frames_per_stop: 3 } },
  };
  const $ = (id) => document.getElementById(id);
  const state = { active: null, shown: null, timer: null };

  function text(tag, value, cls) {
    const node = document.createElement(tag);
    node.textContent = value === null || value === undefined ? "" : String(value);
    if (cls) node.className = cls;
    return node;
  }

  function link(href, label, onClick) {
    const a = document.createElement("a");
    a.href = href;
    a.textContent = label;
    if (onClick) a.addEventListener("click", onClick);
    else a.target = "_blank";
    return a;
  }

  const { headers, call } = window.posecell;
  const showFailure = (p) => window.posecell.showFailure($("test-failure"), p);
  const clearFailure = () => window.posecell.clearFailure($("test-failure"));

  function fillDefaults() {
    const d = DEFAULTS[$("test-kind").value][$("test-mode").value];
    $("test-params").value = JSON.stringify(d);
  }

  async function start() {
    clearFailure();
    let params;
    try {
      params = JSON.parse($("test-params").value || "{}");
      if (typeof params !== "object" || params === null || Array.isArray(params)) throw new Error("not an object");
    } catch (e) {
      showFailure({ reason: "bad_input", message: `the parameters must be a JSON object, e.g. {"laps": 1} (${e.message})` });
      return;
    }
    params.mode = $("test-mode").value;
    $("test-start").disabled = true;
    try {
      const t = await call(`tests/${encodeURIComponent($("test-kind").value)}`, {
        method: "POST", headers: headers(), body: JSON.stringify(params),
      });
      state.active = t.id;
    } catch (e) {
      showFailure(e);
    } finally {
      $("test-start").disabled = false;
      poll();
    }
  }

  async function stop() {
    if (state.active === null) return;
    clearFailure();
    $("test-stop").disabled = true;
    try {
      await call(`tests/${state.active}/stop`, { method: "POST", headers: headers() });
    } catch (e) {
      showFailure(e);
    } finally {
      poll();
    }
  }

  function showReport(t) {
    state.shown = t.id;
    const frame = $("test-report");
    frame.src = `tests/${t.id}/report`;
    frame.hidden = false;
    $("test-report-note").textContent = `Test ${t.id} (${t.kind}):`;
    $("test-report-note").append(" ", link(`tests/${t.id}/report`, "open in a new tab"));
    for (const row of $("tests-table").tBodies[0].rows) row.classList.toggle("selected", row.dataset.id === String(t.id));
  }

  function renderActive(t) {
    const box = $("test-active");
    if (!t) {
      box.hidden = true;
      $("test-stop").disabled = true;
      return;
    }
    box.hidden = false;
    box.dataset.state = t.status;
    box.dataset.id = String(t.id);
    $("test-active-name").textContent = `Test ${t.id}: ${t.kind}, ${t.mode}`;
    $("test-active-status").textContent = t.status;
    $("test-active-status").dataset.state = t.status;
    $("test-progress").value = Number(t.progress) || 0;
    const msg = t.error ? `${t.progress_message || ""}` : t.progress_message || "";
    $("test-progress-text").textContent = `${Math.round((Number(t.progress) || 0) * 100)} % · ${msg} · ${t.n_samples} samples`;
    $("test-stop").disabled = !(t.status === "running" || t.status === "queued");
    $("test-stop").textContent = t.mode === "record" ? "Stop and analyse" : "Cancel";
  }

  /** The start time as HH:MM:SS (UTC, as stored), the full ISO time as its tooltip. */
  function started(iso) {
    const td = text("td", (iso || "").slice(11, 19));
    td.title = iso || "";
    return td;
  }

  function renderList(tests) {
    const rows = tests.map((t) => {
      const tr = document.createElement("tr");
      tr.dataset.id = String(t.id);
      tr.dataset.status = t.status;
      if (t.id === state.shown) tr.className = "selected";
      const status = text("td", t.status);
      if (t.error) status.title = t.error;
      const report = document.createElement("td");
      if (t.status === "done") {
        report.append(
          link(`tests/${t.id}/report`, "show", (e) => { e.preventDefault(); showReport(t); }),
          link(`tests/${t.id}/report.json`, "JSON"),
          link(`tests/${t.id}/samples`, "CSV"),
        );
      } else if (t.error) {
        report.append(text("span", t.error, "muted"));
      }
      tr.append(
        text("td", t.id, "num"), text("td", t.kind), text("td", t.mode), status,
        text("td", `${Math.round((Number(t.progress) || 0) * 100)} %`, "num"),
        text("td", t.n_samples, "num"), started(t.created), report,
      );
      return tr;
    });
    if (!rows.length) {
      const tr = document.createElement("tr");
      const td = text("td", "no tests yet", "muted");
      td.colSpan = 8;
      tr.append(td);
      rows.push(tr);
    }
    $("tests-table").tBodies[0].replaceChildren(...rows);
  }

  async function poll() {
    clearTimeout(state.timer);
    let running = false;
    try {
      const data = await call("tests?limit=20");
      const tests = data.tests || [];
      renderList(tests);
      const active = tests.find((t) => t.status === "running" || t.status === "queued");
      const followed = active || tests.find((t) => t.id === state.active) || null;
      running = Boolean(active);
      if (active) state.active = active.id;
      renderActive(followed);
      // a test followed here that has just finished: show its report at once
      if (followed && followed.status === "done" && state.shown !== followed.id && state.active === followed.id) {
        showReport(followed);
      }
    } catch (e) {
      showFailure(e);
    } finally {
      state.timer = setTimeout(poll, running ? FAST_MS : SLOW_MS);
    }
  }

  function init() {
    $("test-kind").addEventListener("change", fillDefaults);
    $("test-mode").addEventListener("change", fillDefaults);
    $("test-start").addEventListener("click", start);
    $("test-stop").addEventListener("click", stop);
    fillDefaults();
    poll();
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
