/* The blocks page's inboxes: every capture of each schedule and what became of it
   (processed with its job, rejected or ignored with why, still arriving, new), refreshed
   every few seconds. Starts itself on a page with an #inboxes element. */
(function () {
  "use strict";
  const O = window.Orchard;
  const el = O.el;
  const REFRESH_MS = 10000;
  const FATE_LABEL = { processed: "processed", rejected: "rejected", arriving: "still arriving", new: "new", ignored: "ignored" };

  function captureRow(c) {
    let detail;
    if (c.job_id) {
      detail = [el("a", { href: "/jobs/" + encodeURIComponent(c.job_id), text: "job " + c.job_id.slice(0, 8) }), " ",
        O.stateBadge({ state: c.job_state })];
      if (c.reason) detail.push(" " + c.reason);
    } else {
      detail = [c.reason || ""];
    }
    return el("tr", { "data-capture": c.file, "data-fate": c.fate }, [
      el("td", { class: "text", text: c.file }),
      el("td", { class: "text" }, [el("span", { class: "fate fate-" + c.fate, text: FATE_LABEL[c.fate] || c.fate })]),
      el("td", { class: "text reason" }, detail),
      el("td", { class: "text", text: O.when(c.seen_at) }),
    ]);
  }

  function scheduleSection(s) {
    const counts = Object.entries(s.capture_counts || {}).filter(([, n]) => n).map(([f, n]) => `${n} ${FATE_LABEL[f] || f}`);
    const head = el("tr", {}, ["File", "Fate", "Job or why", "Handled"].map((h) => el("th", { class: "text", text: h })));
    const caps = s.captures || [];
    return el("section", { class: "block", "data-schedule": s.id }, [
      el("h3", { text: s.inbox }),
      el("p", { class: "small", text: `cron ${s.cron} · ${s.paused ? "paused" : "next scan " + O.when(s.next_run_at)} · ${counts.join(", ") || "no captures yet"}` }),
      caps.length
        ? el("div", { class: "scroll" }, [el("table", { class: "data captures" }, [el("thead", {}, [head]), el("tbody", {}, caps.map(captureRow))])])
        : null,
    ]);
  }

  async function refresh(root) {
    try {
      const list = await O.api("/v1/schedules");
      const full = await Promise.all(list.map((s) => O.api("/v1/schedules/" + encodeURIComponent(s.id))));
      root.replaceChildren(...(full.length ? [el("h2", { text: "Inboxes" }), ...full.map(scheduleSection)] : []));
      root.dataset.loaded = String(full.length);
    } catch (err) {
      root.dataset.error = err.message;
    }
  }

  function start() {
    const root = document.getElementById("inboxes");
    if (!root) return;
    refresh(root);
    setInterval(() => { if (!document.hidden) refresh(root); }, REFRESH_MS);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();
