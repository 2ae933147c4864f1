/* posecell dashboard: the robot model card (vanilla JS, the calls are cards.js's, nothing from outside).
 *
 * The robot calibration session over the API: POST /calibration/robot/session plans poses (its
 * observability is shown), POST …/session/run visits, records and solves them in the simulated cell,
 * POST …/session/samples records one at the robot's resting pose (a real robot's own program moves
 * it), POST …/session/solve identifies the errors, POST …/session/save stores the model,
 * DELETE …/session discards it; POST /calibration/robot/verify is the shift's check of the stored
 * model. GET …/session every second while the session runs or solves (every 5 s otherwise) keeps
 * the progress and the result current. Every failure is shown as its `reason` and `message`.
 */
"use strict";

(() => {
  const FAST_MS = 1000;
  const SLOW_MS = 5000;
  const SESSION = "calibration/robot/session";
  const $ = (id) => document.getElementById(id);
  const state = { session: null, timer: null, busy: false };

  const { headers, call } = window.posecell;
  const showFailure = (p) => window.posecell.showFailure($("rc-failure"), p);

  const mm = (v, digits = 3) => (v === null || v === undefined ? "–" : `${Number(v).toFixed(digits)} mm`);
  const deg = (v, digits = 4) => (v === null || v === undefined ? "–" : `${Number(v).toFixed(digits)}°`);

  const act = (action) =>
    window.posecell.act({ box: "rc-failure", state, render: () => render(state.session), refresh: poll }, action);

  function plan() {
    return act(async () => {
      const body = {
        mode: $("rc-mode").value,
        n_poses: Number($("rc-poses").value),
        n_holdout: Number($("rc-holdout").value),
      };
      state.session = await call(SESSION, { method: "POST", headers: headers(), body: JSON.stringify(body) });
      $("rc-verify-text").hidden = true;
    });
  }

  const post = (path) => () => act(() => call(`${SESSION}${path}`, { method: "POST", headers: headers() }));

  function discard() {
    return act(async () => {
      await call(SESSION, { method: "DELETE", headers: headers() });
      state.session = null;
    });
  }

  function verify() {
    return act(async () => {
      const box = $("rc-verify-text");
      box.hidden = false;
      box.dataset.verdict = "running";
      box.textContent = "verifying: re-measuring stored poses…";
      let v;
      try {
        v = await call("calibration/robot/verify", { method: "POST", headers: headers(), body: "{}" });
      } catch (e) {
        box.hidden = true;
        throw e;
      }
      box.dataset.verdict = v.verdict;
      box.textContent = `Verification of model version ${v.model_version}: ${v.verdict} — drift at most `
        + `${mm(v.drift.position_max_mm)} / ${deg(v.drift.orientation_max_deg)} over ${v.poses.length} poses `
        + `(thresholds ${mm(v.threshold_mm, 2)} / ${deg(v.threshold_deg, 3)}; the nominal model: `
        + `${mm(v.nominal.position_max_mm)}).`;
    });
  }

  function render(s) {
    const running = Boolean(s && (s.status === "running" || s.status === "solving"));
    const hold = state.busy || running;
    const program = s ? s.mode === "program" : $("rc-mode").value === "program";
    $("rc-plan").disabled = hold;
    $("rc-run").disabled = hold || !s || !program || s.status === "solved";
    $("rc-sample").disabled = hold || !s || program;
    $("rc-solve").disabled = hold || !s || s.n_samples === 0;
    $("rc-save").disabled = hold || !s || s.status !== "solved";
    $("rc-discard").disabled = state.busy || !s;
    $("rc-verify").disabled = hold;
    const box = $("rc-active");
    if (!s) {
      box.hidden = true;
      box.dataset.state = "none";
      $("rc-plan-text").textContent = "No session: plan one.";
      $("rc-result").hidden = true;
      return;
    }
    box.hidden = false;
    box.dataset.state = s.status;
    $("rc-name").textContent = `${s.robot}, ${s.mode}: ${s.n_poses} + ${s.n_holdout} poses`;
    $("rc-status").textContent = s.status;
    $("rc-status").dataset.state = s.status === "failed" ? "failed" : s.status === "solved" ? "ok" : "starting";
    $("rc-progress").value = Number(s.progress) || 0;
    const skipped = s.skipped.length ? ` · ${s.skipped.length} skipped` : "";
    $("rc-progress-text").textContent = `${Math.round((Number(s.progress) || 0) * 100)} % · `
      + `${s.progress_message || ""} · ${s.n_samples} samples${skipped}`
      + (s.restored ? " · restored after a restart" : "");
    const ob = s.observability || {};
    const frozen = (ob.frozen_structural || []).join(", ");
    $("rc-plan-text").textContent = `Plan: condition ${ob.condition}, ${ob.n_identifiable} parameters identifiable`
      + (frozen ? `; held at nominal (not separable from the base and tool): ${frozen}` : "") + ".";
    const r = s.result;
    const out = $("rc-result");
    out.hidden = !r;
    if (r) {
      const before = r.holdout.before;
      const after = r.holdout.after;
      out.textContent = `Held-out poses (${r.n_holdout}): position ${mm(before.position_mean_mm)} → `
        + `${mm(after.position_mean_mm, 4)} mean (${mm(before.position_max_mm)} → ${mm(after.position_max_mm, 4)} max), `
        + `orientation ${deg(before.orientation_mean_deg)} → ${deg(after.orientation_mean_deg, 5)} mean; `
        + `${r.n_calibration} calibration poses, condition ${r.condition}.`;
    }
  }

  async function stored() {
    const c = await call("calibration");
    const robot = c.robot || {};
    $("rc-stored").textContent = robot.present
      ? `Stored robot model: version ${robot.version} (${robot.source}).`
      : "No robot model is stored yet: compensation and verification need one.";
  }

  async function poll() {
    clearTimeout(state.timer);
    let running = false;
    try {
      const s = await call(SESSION, {}, true);
      state.session = s;
      running = Boolean(s && (s.status === "running" || s.status === "solving"));
      if (!state.busy) render(s);
      await stored();
    } catch (e) {
      showFailure(e);
    } finally {
      state.timer = setTimeout(poll, running ? FAST_MS : SLOW_MS);
    }
  }

  function init() {
    $("rc-plan").addEventListener("click", plan);
    $("rc-run").addEventListener("click", post("/run"));
    $("rc-sample").addEventListener("click", post("/samples"));
    $("rc-solve").addEventListener("click", post("/solve"));
    $("rc-save").addEventListener("click", post("/save"));
    $("rc-discard").addEventListener("click", discard);
    $("rc-verify").addEventListener("click", verify);
    $("rc-mode").addEventListener("change", () => render(state.session));
    poll();
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", init);
  else init();
})();
