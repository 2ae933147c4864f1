/* posecell dashboard: the recordings card (vanilla JS, beside app.js, nothing from outside).
 *
 * GET /recordings every second while one runs (every 5 s otherwise) fills the table; POST /recordings
 * starts one with the form's limits, POST /recordings/{id}/stop ends it, DELETE /recordings/{id}
 * removes an ended one. The API token is the one typed into the "Triggered measurement" card; every
 * failure is shown as its `reason` and `message` (cards.js).
 */
"use strict";

(() => {
  const FAST_MS = 1000;
  const SLOW_MS = 5000;
  const $ = (id) => document.getElementById(id);
  const { headers, call, act } = window.posecell;

  const card = {
    box: "rec-failure",
    state: { busy: false, recordings: [], timer: null },
    render,
    refresh,
  };

  function cell(value) {
    const td = document.createElement("td");
    td.textContent = value === null || value === undefined ? "" : String(value);
    return td;
  }

  function sum(rec, key) {
    return Object.values(rec.cameras || {}).reduce((n, c) => n + (c[key] || 0), 0);
  }

  function button(label, onClick) {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = label;
    b.disabled = card.state.busy;
    b.addEventListener("click", onClick);
    return b;
  }

  function render() {
    const rows = card.state.recordings.map((rec) => {
      const tr = document.createElement("tr");
      tr.dataset.id = rec.id;
      tr.dataset.state = rec.state;
      const state = cell(rec.state);
      if (rec.message) state.title = rec.message;
      const actions = document.createElement("td");
      if (rec.state === "recording") {
        actions.append(button("Stop", () => act(card, () => call(`recordings/${rec.id}/stop`, { method: "POST", headers: headers() }))));
      } else {
        actions.append(button("Delete", () => act(card, () => call(`recordings/${rec.id}`, { method: "DELETE", headers: headers() }))));
      }
      tr.append(cell(rec.id), cell(rec.label), state, cell(sum(rec, "written")), cell(sum(rec, "dropped")),
        cell(rec.robot_samples), cell(rec.folder), actions);
      return tr;
    });
    if (!rows.length) {
      const tr = document.createElement("tr");
      const td = cell("no recordings yet");
      td.colSpan = 8;
      td.className = "muted";
      tr.append(td);
      rows.push(tr);
    }
    $("rec-table").tBodies[0].replaceChildren(...rows);
    $("rec-start").disabled = card.state.busy;
  }

  async function refresh() {
    try {
      const data = await call("recordings");
      card.state.recordings = data.recordings;
    } catch (e) {
      window.posecell.showFailure($("rec-failure"), e);
    }
    render();
    clearTimeout(card.state.timer);
    const running = card.state.recordings.some((r) => r.state === "recording");
    card.state.timer = setTimeout(refresh, running ? FAST_MS : SLOW_MS);
  }

  function start() {
    const body = {
      max_frames: Number($("rec-frames").value),
      max_seconds: Number($("rec-seconds").value),
      every_n: Number($("rec-every").value),
      format: $("rec-format").value,
      label: $("rec-label").value.trim(),
    };
    return act(card, () => call("recordings", { method: "POST", headers: headers(), body: JSON.stringify(body) }));
  }

  $("rec-start").addEventListener("click", start);
  refresh();
})();
