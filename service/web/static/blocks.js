/* The blocks page: the farm's orchard blocks with their captures in order, then every
   uploaded block with its jobs, refreshed every few seconds. */
(function () {
  "use strict";
  const O = window.Orchard;
  const el = O.el;
  const REFRESH_MS = 3000;

  function jobRow(job) {
    const cancel =
      job.state === "queued" || job.state === "running"
        ? el("button", { class: "secondary", type: "button", text: "Cancel", onclick: () => cancelJob(job.id) })
        : null;
    return el("tr", { "data-job": job.id }, [
      el("td", { class: "text" }, [el("a", { href: job.links.page, text: job.id })]),
      el("td", { class: "text" }, [O.stateBadge(job), " ", O.progress(job)]),
      el("td", { text: job.n_trees === null || job.n_trees === undefined ? "–" : O.fmt(job.n_trees) }),
      el("td", { class: "text", text: job.capture || (job.schedule_id ? "schedule" : "upload") }),
      el("td", { class: "text", text: O.when(job.created_at) }),
      el("td", { class: "text", text: O.when(job.finished_at) }),
      el("td", { class: "text" }, [cancel]),
    ]);
  }

  const SOURCES = { file: "from the file", given: "as sent", upload: "day it arrived" };

  function captureRow(c) {
    const n = c.counts;
    return el("tr", { "data-capture": c.id }, [
      el("td", { text: String(c.seq) }),
      el("td", { class: "text", text: (c.captured_at || "–") + (c.captured_at_source ? ` (${SOURCES[c.captured_at_source] || c.captured_at_source})` : "") }),
      el("td", { class: "text" }, [el("span", { class: "state state-" + c.state, text: c.state })]),
      el("td", { class: "text", text: n ? `${n.same} same, ${n.new} new, ${n.replanted} replanted, ${n.removed} removed` : (c.error || "–") }),
      el("td", { class: "text" }, [el("a", { href: c.links.page, text: "job " + c.job_id.slice(0, 8) })]),
    ]);
  }

  /* The orchard blocks (none: the section stays empty, as the page was before them). */
  function renderOrchard(blocks, captures) {
    const head = el("tr", {}, ["#", "Captured", "State", "Trees", "Job"].map((h) => el("th", { class: h === "#" ? "" : "text", text: h })));
    const parts = blocks.map((b, k) => {
      const cs = captures[k] || [];
      const history = b.links["history.parquet"] ? [" · ", el("a", { href: b.links["history.parquet"], download: "", text: "history (Parquet)" })] : [];
      return el("section", { class: "block", "data-orchard-block": b.id }, [
        el("h2", { text: b.name }),
        el("p", { class: "small" }, [`orchard block · ${b.n_captures} capture(s), ${b.n_done} processed` + (b.last_captured_at ? `, latest ${b.last_captured_at}` : ""), ...history]),
        cs.length ? el("table", { class: "data" }, [el("thead", {}, [head]), el("tbody", {}, cs.map(captureRow))])
                  : el("p", { class: "small", text: "No captures yet." }),
      ]);
    });
    let root = document.getElementById("orchardblocks");
    if (!root) { // above the uploaded blocks
      const blocksDiv = document.getElementById("blocks");
      root = blocksDiv.parentNode.insertBefore(el("div", { id: "orchardblocks" }), blocksDiv);
    }
    root.replaceChildren(...parts);
  }

  async function refreshOrchard() {
    const blocks = await O.api("/v1/orchard-blocks");
    const captures = await Promise.all(blocks.map((b) => O.api(b.links.captures)));
    renderOrchard(blocks, captures);
  }

  async function cancelJob(id) {
    try {
      await O.api("/v1/jobs/" + encodeURIComponent(id), { method: "DELETE" });
    } catch (err) {
      document.getElementById("updated").textContent = "Could not cancel: " + err.message;
    }
    refresh();
  }

  function render(blocks, jobs) {
    const byBlock = new Map();
    for (const j of jobs) {
      if (!byBlock.has(j.block_id)) byBlock.set(j.block_id, []);
      byBlock.get(j.block_id).push(j);
    }
    const root = document.getElementById("blocks");
    const parts = [];
    if (!blocks.length) parts.push(el("p", { text: "No blocks yet: upload one with POST /v1/blocks or let a schedule find captures." }));
    for (const b of blocks) {
      const js = (byBlock.get(b.id) || []).sort((a, c) => (c.created_at || "").localeCompare(a.created_at || ""));
      const head = el("tr", {}, ["Job", "State", "Trees", "From", "Submitted", "Finished", ""].map((h) => el("th", { class: h === "Trees" ? "" : "text", text: h })));
      parts.push(
        el("section", { class: "block", "data-block": b.id }, [
          el("h2", { text: b.filename || b.id }),
          el("p", { class: "small", text: `${b.id} · ${O.fmt(b.n_points)} points · ${(b.size_bytes / 1e6).toFixed(1)} MB · uploaded ${O.when(b.created_at)}` }),
          js.length
            ? el("table", { class: "data" }, [el("thead", {}, [head]), el("tbody", {}, js.map(jobRow))])
            : el("p", { class: "small", text: "No jobs for this block." }),
        ])
      );
    }
    root.replaceChildren(...parts);
  }

  async function refresh() {
    const status = document.getElementById("updated");
    try {
      // a list, or a page of one ({items, total, ...})
      const items = (x) => (Array.isArray(x) ? x : x.items || []);
      const [blocks, jobs] = (await Promise.all([O.api("/v1/blocks?limit=1000"), O.api("/v1/jobs?limit=1000")])).map(items);
      render(blocks, jobs);
      await refreshOrchard();
      const active = jobs.filter((j) => j.state === "queued" || j.state === "running").length;
      status.textContent = `${blocks.length} block(s), ${jobs.length} job(s), ${active} queued or running · updated ${new Date().toLocaleTimeString()}`;
    } catch (err) {
      status.textContent = "Could not refresh: " + err.message + " (trying again)";
    }
  }

  O.blocks = function () {
    refresh();
    setInterval(() => {
      if (!document.hidden) refresh();
    }, REFRESH_MS);
  };

  if (document.body.dataset.page === "blocks") O.blocks();  // (no inline script starts it: the CSP runs none)
})();
