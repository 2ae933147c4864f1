/* posecell dashboard: the hand-eye calibration card (vanilla JS, the calls are cards.js's, nothing from outside).
 *
 * The guided session over the API: POST /calibration/handeye/session proposes poses around the field,
 * POST …/move/{k} moves the simulated arm to one (a real robot is moved by its own program),
 * POST …/samples records a sample at the robot's resting pose (409 robot_moving while it moves: tried
 * again until it rests), POST …/solve?apply=true solves X and Z and uses them, DELETE discards.
 * "Visit all" does move, wait, record for every proposal in turn, skipping the ones the arm cannot
 * reach (the service says so), as an operator would. Every failure is shown as its `reason` and `message`.
 */
"use strict";

(() => {
  const SESSION = "calibration/handeye/session";
  const REST_TIMEOUT_MS = 8000;
  const $ = (id) => document.getElementById(id);
  const POLL_MS = 5000;
  const state = { session: null, rows: [], busy: false, simulated: false, timer: null };
  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

  const { headers, call } = window.posecell;
  const showFailure = (p) => window.posecell.showFailure($("he-failure"), p);

  const fixed = (values, digits) => values.map((v) => Number(v).toFixed(digits)).join(", ");

  /** Record a sample as soon as the service finds the arm at rest (it refuses while the arm moves). */
  async function record() {
    const deadline = Date.now() + REST_TIMEOUT_MS;
    for (;;) {
      try {
        return await call(`${SESSION}/samples`, { method: "POST", headers: headers() });
      } catch (e) {
        if (e.reason !== "robot_moving" || Date.now() > deadline) throw e;
        await sleep(100);
      }
    }
  }

  async function move(k) {
    state.rows[k] = "moving";
    render();
    try {
      const m = await call(`${SESSION}/move/${k}`, { method: "POST", headers: headers() });
      await sleep(m.duration_s * 1000);
      state.rows[k] = "arrived";
    } catch (e) {
      state.rows[k] = e.status === 422 ? "unreachable" : "";
      throw e;
    } finally {
      render();
    }
  }

  const act = (action) => window.posecell.act({ box: "he-failure", state, render, refresh }, action);

  const start = () => act(async () => {
    const body = JSON.stringify({ n_poses: Number($("he-poses").value) });
    state.session = await call(SESSION, { method: "POST", headers: headers(), body });
    state.rows = state.session.proposals.map(() => "");
    $("he-result").hidden = true;
  });

  const sample = () => act(async () => {
    await record();
    const k = state.rows.indexOf("arrived");
    if (k >= 0) state.rows[k] = "recorded";
  });

  const visitAll = () => act(async () => {
    const skipped = [];
    for (let k = 0; k < state.rows.length; k += 1) {
      if (state.rows[k] === "recorded") continue;
      $("he-state").textContent = `visiting proposal ${k + 1} of ${state.rows.length}…`;
      try {
        await move(k);
      } catch (e) {
        if (e.status !== 422) throw e;
        skipped.push(k);  // the plan knows the field, not the arm: this pose is left out
        continue;
      }
      await record();
      state.rows[k] = "recorded";
      render();
    }
    if (skipped.length) {
      showFailure({ reason: "skipped", message: `not reachable, left out: ${skipped.map((k) => `#${k}`).join(", ")}` });
      $("he-failure").classList.add("warn");
    }
  });

  const solve = () => act(async () => {
    const r = await call(`${SESSION}/solve?apply=true`, { method: "POST", headers: headers() });
    const out = $("he-result");
    out.hidden = false;
    out.dataset.version = String(r.applied_version);
    out.textContent = `Applied as hand-eye version ${r.applied_version} (${r.method}, ${r.rms_px_per_sample.length} samples): `
      + `camera in the flange at ${fixed(r.T_flange_camera.slice(0, 3).map((row) => row[3]), 2)} mm, field in the base at `
      + `${fixed(r.T_base_field.slice(0, 3).map((row) => row[3]), 2)} mm; position residual ${Number(r.rms_position_mm).toFixed(3)} mm rms `
      + "(the arm's own errors).";
  });

  const discard = () => act(async () => {
    await call(SESSION, { method: "DELETE", headers: headers() });
    state.session = null;
    state.rows = [];
  });

  function render() {
    const s = state.session;
    const hold = state.busy;
    $("he-start").disabled = hold;
    $("he-visit").disabled = hold || !s || !state.simulated;
    $("he-sample").disabled = hold || !s;
    $("he-solve").disabled = hold || !s || s.n_samples < 3;
    $("he-discard").disabled = hold || !s;
    if (!s) {
      $("he-state").textContent = "No session: propose poses.";
      $("he-table").tBodies[0].replaceChildren();
      return;
    }
    if (!hold) {
      const q = s.motion;
      $("he-state").textContent = `${s.proposals.length} poses proposed for camera ${s.camera}; ${s.n_samples} samples recorded`
        + (q ? `; rotations up to ${Number(q.max_rotation_deg).toFixed(1)}°, axis spread ${Number(q.axis_spread).toFixed(2)}` : "")
        + (s.n_samples < 3 ? " (3 or more are needed)." : ".")
        + (s.restored ? " Restored after a restart." : "");
    }
    const rows = s.proposals.map((p, k) => {
      const tr = document.createElement("tr");
      tr.dataset.index = String(k);
      tr.dataset.recorded = String(state.rows[k] === "recorded");
      const cell = (value) => {
        const td = document.createElement("td");
        td.textContent = value;
        return td;
      };
      const arm = document.createElement("td");
      if (state.simulated && !["recorded", "unreachable"].includes(state.rows[k])) {
        const b = document.createElement("button");
        b.type = "button";
        b.textContent = "Move";
        b.disabled = hold;
        b.addEventListener("click", () => act(() => move(k)));
        arm.append(b, " ");
      }
      arm.append(state.rows[k] || "");
      tr.append(cell(String(k)), cell(fixed(p.xyz_mm, 1)), cell(fixed(p.kuka_abc_deg, 1)), arm);
      return tr;
    });
    $("he-table").tBodies[0].replaceChildren(...rows);
  }

  async function refresh() {
    clearTimeout(state.timer);
    try {
      const [s, health] = await Promise.all([call(SESSION, {}, true), call("health")]);
      state.simulated = Boolean(health.robot && health.robot.driver === "sim");
      if (!s) state.rows = [];
      else if (state.rows.length !== s.proposals.length) state.rows = s.proposals.map(() => "");
      state.session = s;
    } catch (e) {
      showFailure(e);
    }
    if (!state.busy) render();
    state.timer = setTimeout(() => { if (!state.busy) refresh(); else state.timer = null; }, POLL_MS);
  }

  function init() {
    $("he-start").addEventListener("click", start);
    $("he-visit").addEventListener("click", visitAll);
    $("he-sample").addEventListener("click", sample);
    $("he-solve").addEventListener("click", solve);
    $("he-discard").addEventListener("click", discard);
    refresh();
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
