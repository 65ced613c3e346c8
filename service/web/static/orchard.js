/* Orchard pages: what every page shares (JSON with the session cookie, formatting). */
(function () {
  "use strict";
  const O = (window.Orchard = window.Orchard || {});

  O.csrf = function () {
    const m = document.querySelector('meta[name="csrf-token"]');
    return m ? m.content : "";
  };

  /* GET (or another method) a JSON resource of this server with the session cookie;
     a lost session sends the browser to sign in again. */
  O.api = async function (path, options) {
    // signing out: the pages' refreshes ask nothing more (the ended session would answer 401)
    if (O.leaving) return new Promise(() => {});
    const opts = Object.assign({ credentials: "same-origin", headers: {} }, options || {});
    if (opts.method && opts.method !== "GET") opts.headers["X-CSRF-Token"] = O.csrf();
    const resp = await fetch(path, opts);
    if (resp.status === 401) {
      window.location.assign("/signin?next=" + encodeURIComponent(window.location.pathname));
      throw new Error("signed out");
    }
    const body = await resp.json().catch(() => ({}));
    if (!resp.ok) throw new Error(body.detail || resp.status + " " + resp.statusText);
    return body;
  };

  document.addEventListener("submit", (e) => {
    if (e.target && e.target.classList && e.target.classList.contains("signout")) O.leaving = true;
  });

  O.el = function (tag, attrs, children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === null || v === undefined) continue;
      if (k === "text") e.textContent = v;
      else if (k === "class") e.className = v;
      else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
      else e.setAttribute(k, v);
    }
    for (const c of [].concat(children || [])) {
      if (c === null || c === undefined) continue;
      e.appendChild(typeof c === "string" ? document.createTextNode(c) : c);
    }
    return e;
  };

  O.fmt = function (v, digits) {
    if (v === null || v === undefined || Number.isNaN(v)) return "–";
    if (typeof v !== "number") return String(v);
    if (Number.isInteger(v) && digits === undefined) return v.toLocaleString("en");
    return v.toFixed(digits === undefined ? 2 : digits);
  };

  O.when = function (iso) {
    if (!iso) return "–";
    const d = new Date(iso);
    return Number.isNaN(d.getTime()) ? iso : d.toLocaleString();
  };

  O.stateBadge = function (job) {
    return O.el("span", { class: "state state-" + job.state, text: job.state });
  };

  O.progress = function (job) {
    const total = job.tiles_total || 0;
    if (job.state !== "running" && job.state !== "queued") return null;
    return O.el("span", {}, [
      O.el("progress", { max: String(Math.max(total, 1)), value: String(job.tiles_done || 0) }),
      " " + (job.tiles_done || 0) + "/" + total + " tiles",
    ]);
  };
})();
