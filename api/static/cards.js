/* posecell dashboard: what the workflow cards (tests.js, handeye.js, robot.js) share, loaded before them.
 *
 * `posecell.call` fetches JSON and resolves the body, or throws {reason, message, status}: the
 * service's own reason and sentence, or ours when it does not answer; a 404 resolves null when the
 * caller says it is no failure (no session yet). `posecell.headers` carries the API token typed into
 * the "Triggered measurement" card. `posecell.showFailure` / `clearFailure` fill a card's failure box;
 * `posecell.act` runs a button's action with the card's buttons held and its failure shown.
 */
"use strict";

window.posecell = (() => {
  function headers() {
    const field = document.getElementById("token");
    const token = (field && field.value.trim()) || "";
    const h = { "Content-Type": "application/json" };
    if (token) h.Authorization = `Bearer ${token}`;
    return h;
  }

  async function call(url, options = {}, missingOk = false) {
    let res;
    try {
      res = await fetch(url, { cache: "no-store", ...options });
    } catch (e) {
      throw { reason: "network_error", message: `the service at ${location.host} does not answer (${e && e.message})` };
    }
    const body = await res.text();
    let data = null;
    try { data = body ? JSON.parse(body) : null; } catch (_) { data = null; }
    if (res.status === 404 && missingOk) return null;
    if (!res.ok) {
      if (data && data.reason) {
        throw { reason: String(data.reason), message: String(data.message || `HTTP ${res.status}`), status: res.status };
      }
      throw { reason: `http_${res.status}`, message: body.trim().slice(0, 200) || `HTTP ${res.status}`, status: res.status };
    }
    return data;
  }

  function showFailure(box, p) {
    const reason = document.createElement("span");
    reason.className = "reason";
    reason.textContent = p.reason || "error";
    const message = document.createElement("span");
    message.textContent = p.message || "no message was given";
    box.replaceChildren(reason, message);
    box.dataset.reason = p.reason || "error";
    box.hidden = false;
  }

  function clearFailure(box) {
    box.hidden = true;
    box.dataset.reason = "";
    box.classList.remove("warn");
  }

  /** One button's action on a card: its failure box (`card.box`, an id) cleared, `card.state.busy`
   * while it runs (the card's `render` holds its buttons then), a failure shown, `refresh` after. */
  async function act(card, action) {
    const box = document.getElementById(card.box);
    clearFailure(box);
    card.state.busy = true;
    card.render();
    try {
      await action();
    } catch (e) {
      showFailure(box, e);
    } finally {
      card.state.busy = false;
      await card.refresh();
    }
  }

  return { headers, call, showFailure, clearFailure, act };
})();
