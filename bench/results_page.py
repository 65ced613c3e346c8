"""bench/results.md, the PNG plots, and the section of docs/benchmarks.md between the bench markers."""

from __future__ import annotations

import math
import re
from pathlib import Path

START, END = "<!-- bench:start -->", "<!-- bench:end -->"

#: what the paper reports (Westling et al.), real and virtual data
PAPER = {
    "trunk_f1": {"real": 0.774, "virtual": 0.687},
    "trunk_precision": {"real": 0.758, "virtual": 0.586},
    "trunk_recall": {"real": 0.790, "virtual": 0.830},
    "trunk_mean_distance": {"real": 0.357, "virtual": 0.452},
    "v_measure": {"real": 0.915, "virtual": 0.884},
    "wood_f1": {"real": 0.482, "virtual": 0.488},
}
METHOD_NAMES = {
    "ours": "ours",
    "closest_trunk": "closest-trunk baseline",
    "paper_with_our_trunks": "paper's segmentation + wood steps, from our trunks",
    "paper_as_published": "paper as published (re-implemented, incl. its trunk finding)",
}


def _f(x, digits=2) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    return f"{x:.{digits}f}"


def _cell(text: str, limit: int = 140) -> str:
    """Text safe inside a Markdown table cell."""
    text = " ".join(str(text).replace("|", "/").split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _cores(r: dict) -> str:
    cpu, wall = r.get("cpu_s"), r.get("wall_s")
    return f"{cpu / wall:.2f}" if cpu and wall else "–"


def _gib(b) -> str:
    return "–" if not b else f"{b / 2**30:.2f} GiB"


def _each_gib(peaks) -> str:
    """Every process's peak [bytes], largest first: "1.20 / 1.18 GiB"."""
    return "–" if not peaks else " / ".join(f"{b / 2**30:.2f}" for b in sorted(peaks, reverse=True)) + " GiB"


def _other_processes(sampled: dict | None) -> str:
    """Sampled peaks of the processes that are neither the submitting one nor a dask worker."""
    if sampled is None:
        return "–"
    others = [(label, b) for label, peaks in sorted(sampled.items()) if label not in ("main", "dask-worker") for b in peaks]
    return ", ".join(f"{label} {b / 2**30:.2f} GiB" for label, b in others) or "none"


def _stage_split(run: dict) -> str:
    """"tiling / processing / merge+write" seconds of a tiled run."""
    t = run.get("timings") or {}
    return " / ".join(f"{t[k]:.1f} s" for k in ("tile", "process", "merge_write") if k in t)


def _mpts(x) -> str:
    return f"{x / 1e6:.2f} M/s"


# ----------------------------------------------------------------------------- plots


def _pyplot():
    """matplotlib.pyplot on the headless Agg backend (imported only when plotting)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_accuracy(results: list[dict], path: Path) -> None:
    plt = _pyplot()
    import numpy as np

    metrics = (("trunk_f1", "trunk F1"), ("v_measure", "v-measure"), ("wood_f1", "wood F1"))
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5), sharey=True)
    for row, (key, label) in enumerate((("noise", "noise σ [m]"), ("spacing", "tree spacing [m]"))):
        xs = sorted({r[key] for r in results})
        for col, (metric, mlabel) in enumerate(metrics):
            ax = axes[row, col]
            for method, style in (("ours", "o-"), ("closest_trunk", "s--"), ("paper_as_published", "^:")):
                ys = []
                for x in xs:
                    vals = [r["methods"][method].get(metric, np.nan) for r in results
                            if r[key] == x and method in r["methods"] and "error" not in r["methods"][method]]
                    ys.append(np.nanmean(vals) if vals else np.nan)
                ax.plot(xs, ys, style, label=METHOD_NAMES[method])
            paper = PAPER[metric]["virtual"]
            ax.axhline(paper, color="grey", lw=1, ls="-.", label="paper (virtual data)")
            ax.set_xlabel(label)
            ax.set_title(mlabel)
            ax.set_ylim(0, 1.02)
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8, loc="lower left")
    fig.suptitle("Accuracy on generated blocks (mean over the other parameter)")
    _save(fig, path)


def plot_stages(stand: dict, path: Path) -> None:
    plt = _pyplot()

    stages = stand["stages"]
    names = list(stages)
    secs = [stages[n] for n in names]
    fig, ax = plt.subplots(figsize=(8, 3.6))
    left = 0.0
    for name, s in zip(names, secs):
        ax.barh([0], [s], left=left, label=f"{name} {s:.2f} s")
        left += s
    ax.set_yticks([])
    ax.set_xlabel("seconds (one core)")
    ax.set_title(f"3-tree stand, {stand['block']['n_points']:,} points: {stand['median_s']:.2f} s (paper: {stand['paper_s']:.0f} s)")
    ax.legend(ncol=4, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.25))
    _save(fig, path)


def plot_scaling(scaling: dict, path: Path) -> None:
    plt = _pyplot()
    import numpy as np

    rows = scaling["rows"]
    n = np.array([r["n_points"] for r in rows], float)
    t = np.array([r["wall_s"] for r in rows], float)
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4))
    a1.loglog(n, t, "o-", label=f"measured (slope {scaling['exponent']:.2f})")
    if len(n) >= 1:
        a1.loglog(n, t[0] * n / n[0], ":", color="grey", label="linear")
    a1.set_xlabel("points")
    a1.set_ylabel("wall time [s]")
    a1.set_title(f"time vs points ({scaling['workers']} workers, {scaling['tile_size']:g} m tiles)")
    a1.grid(alpha=0.3, which="both")
    a1.legend()
    a2.plot(n / 1e6, [r["main_maxrss"] / 2**30 for r in rows], "o-", label="submitting process (scheduler in it)")
    a2.plot(n / 1e6, [max(r["worker_maxrss"] or [0]) / 2**30 for r in rows], "s-", label="largest worker")
    a2.plot(n / 1e6, [r["tree_peak_total"] / 2**30 for r in rows], "^--", label="all processes (sampled)")
    a2.axhline(2.0, color="red", lw=1, ls=":", label="2 GB target per worker")
    a2.set_xlabel("million points")
    a2.set_ylabel("peak RSS [GiB]")
    a2.set_title("peak memory")
    a2.grid(alpha=0.3)
    a2.legend(fontsize=8)
    _save(fig, path)


# ----------------------------------------------------------------------------- text


def diameter_table(blocks: list[dict]) -> list[str]:
    """Lines of the "Trunk diameters" table: ours against the simulator's trunks, per noise
    level over all spacings (empty when the results carry no diameter errors)."""
    rows = {}
    for r in blocks:
        v = r["methods"].get("ours", {})
        if v.get("trunk_diameter_n"):
            rows.setdefault(r["noise"], []).append(v)
    if not rows:
        return []
    out = ["", "### Trunk diameters", "",
           ("Ours (`trunk_diameter_m`, a noise-corrected circle fit to a 0.1 m slice at 0.3 m) against the "
            "simulator's trunk at that height (about 0.12–0.30 m thick), over the matched trees of the blocks above, "
            "by noise level (all spacings):"), "",
           "| noise [m] | trees compared | not measurable | bias [cm] | mean absolute error [cm] |",
           "| --- | --- | --- | --- | --- |"]
    for noise in sorted(rows):
        vs = rows[noise]
        n = sum(v["trunk_diameter_n"] for v in vs)
        bias = sum(v["trunk_diameter_bias"] * v["trunk_diameter_n"] for v in vs) / n
        mae = sum(v["trunk_diameter_mae"] * v["trunk_diameter_n"] for v in vs) / n
        out.append(f"| {noise:g} | {n} | {sum(v.get('trunk_diameter_unmeasured', 0) for v in vs)} | "
                   f"{100 * bias:+.1f} | {100 * mae:.1f} |")
    return out


def render(data: dict) -> str:
    m = data["machine"]
    out = ["# Benchmark results", ""]
    out.append(f"Generated by `{data['command']}` on {m['date']}; every figure below comes from that run "
               f"(total {data['elapsed_s'] / 60:.1f} min). Blocks are generated by `simulator` "
               "(mobile-scanner sampling, overlapping crowns, grass, slope, posts, a vehicle and a bin, ghosting, outliers).")
    out += ["", "## Machine", "", "| | |", "| --- | --- |"]
    out.append(f"| CPU | {m['cpu']} ({m['logical_cores']} logical cores, {m['usable_cores']} usable) |")
    out.append(f"| RAM | {m['ram_gib']} GiB |")
    out.append(f"| OS | {m['os']} |")
    out.append(f"| Python | {m['python']} |")
    out.append("| libraries | " + ", ".join(f"{k} {v}" for k, v in m["versions"].items()) + " |")
    load = data.get("load")
    if load:
        out.append(f"| load average (1 min) during the run | {load['min']:.1f}–{load['max']:.1f}, mean {load['mean']:.1f} |")
        if load["max"] > m["usable_cores"] + 0.5:
            out += ["", f"**The machine was shared**: the load average exceeded its {m['usable_cores']} cores during the run, "
                    "so other processes competed for the CPU and wall times are pessimistic. CPU seconds "
                    "(user + system of the measured processes) are given next to wall times; they are less affected."]

    acc = data.get("accuracy")
    if acc:
        out += ["", "## Accuracy", ""]
        out.append(f"{len(acc['blocks'])} generated blocks (2 rows of 5 trees, crowns overlapping), noise σ ∈ "
                   f"{{{', '.join(f'{x:g}' for x in acc['noises'])}}} m × spacing ∈ {{{', '.join(f'{x:g}' for x in acc['spacings'])}}} m. "
                   "Trunks match one-to-one within 1 m; v-measure and wood F1 are computed on the true tree points. "
                   "Ours is scored from its Parquet outputs; the baselines run on the same points.")
        out += ["", "| method | trunk precision | trunk recall | trunk F1 | trunk distance [m] | v-measure | wood F1 |",
                "| --- | --- | --- | --- | --- | --- | --- |"]
        for method, s in acc["summary"].items():
            err = f" ({s['n_errors']} failed)" if s.get("n_errors") else ""
            out.append(f"| {METHOD_NAMES[method]}{err} | {_f(s['trunk_precision'])} | {_f(s['trunk_recall'])} | "
                       f"**{_f(s['trunk_f1'])}** | {_f(s['trunk_mean_distance'])} | **{_f(s['v_measure'])}** | **{_f(s['wood_f1'])}** |")
        for kind in ("real", "virtual"):
            out.append(f"| paper, {kind} data (as reported) | {_f(PAPER['trunk_precision'][kind], 3)} | {_f(PAPER['trunk_recall'][kind], 3)} | "
                       f"{_f(PAPER['trunk_f1'][kind], 3)} | {_f(PAPER['trunk_mean_distance'][kind], 3)} | "
                       f"{_f(PAPER['v_measure'][kind], 3)} | {_f(PAPER['wood_f1'][kind], 3)} |")
        out += ["", "The paper as published collapses on these blocks because of their grass: its trunk-finding sources, one per 4 m cell, fall on grass, and each makes a false trunk; on the paper's own setting (bare, flat ground) it finds every trunk ([the paper's setting](accuracy.md#the-papers-method-on-the-papers-setting), `python -m bench.paper_setting`).",
                "", "Per block (trunk F1 / v-measure / wood F1):", "",
                "| noise [m] | spacing [m] | points | ours | closest-trunk | paper steps, our trunks | paper as published |",
                "| --- | --- | --- | --- | --- | --- | --- |"]
        for r in sorted(acc["blocks"], key=lambda r: (r["noise"], r["spacing"])):
            cells = []
            for method in ("ours", "closest_trunk", "paper_with_our_trunks", "paper_as_published"):
                v = r["methods"].get(method)
                if v is None:
                    cells.append("–")
                elif "error" in v:
                    cells.append("error: " + _cell(v["error"], 80))
                else:
                    cells.append(f"{_f(v['trunk_f1'])} / {_f(v['v_measure'])} / {_f(v['wood_f1'])}"
                                 + (" (no trees found)" if v.get("note", "").startswith("no trees") else ""))
            out.append(f"| {r['noise']:g} | {r['spacing']:g} | {r['n_points']:,} | " + " | ".join(cells) + " |")
        out += ["", "![accuracy](accuracy.png)"]
        out += diameter_table(acc["blocks"])

    if data.get("real_data_md"):
        out += ["", data["real_data_md"].rstrip()]

    st = data.get("stand")
    if st:
        b = st["block"]
        out += ["", "## Speed: one 3-tree stand", ""]
        out.append(f"A generated 3-tree stand of {b['n_points']:,} points (5 m spacing, σ = 0.02 m), LAZ in → "
                   f"`trees.parquet` + `points.parquet` out, `workers.job.run_job` in one process pinned to one core, "
                   f"one untimed warm-up run, then the median of {len(st['walls'])} runs ({', '.join(f'{w:.2f}' for w in st['walls'])} s).")
        out += ["", "| | this run | paper |", "| --- | --- | --- |"]
        out.append(f"| time per stand | **{st['median_s']:.2f} s** | {st['paper_s']:.0f} s (avocado stands, their hardware) |")
        out.append(f"| speed-up | {st['paper_s'] / st['median_s']:.0f}× | |")
        out.append(f"| throughput | {_mpts(st['points_per_s'])} | |")
        if st.get("cpu_s"):
            out.append(f"| CPU time (user + system) | {st['cpu_s']:.2f} s | |")
        out.append(f"| peak RSS | {_gib(st['peak_rss'])} | |")
        out.append(f"| trees found / true | {st['n_trees_found']} / {b['n_trees']} | |")
        a = st["accuracy"]
        out.append(f"| trunk F1 / v-measure / wood F1 | {_f(a['trunk_f1'])} / {_f(a['v_measure'])} / {_f(a['wood_f1'])} | 0.774 / 0.915 / 0.482 (real) |")
        out += ["", "Split by stage (each kernel call timed from the outside; *other* is glue, merge and label assembly):", "",
                "| stage | seconds | share |", "| --- | --- | --- |"]
        total = sum(st["stages"].values())
        for name, s in st["stages"].items():
            out.append(f"| {name} | {s:.3f} | {100 * s / total:.0f} % |")
        d = st["decode"]
        out += ["", "Raw LAZ decode of the same file (laspy chunk iteration, one core) and the end-to-end ratio:", "",
                "| reader | points/s | end-to-end ÷ decode |", "| --- | --- | --- |"]
        for key, label in (("laspy_all_fields", "laspy, all point fields"), ("laspy_xyz_only", "laspy, x/y/z only (what the pipeline decodes)"),
                           ("pipeline_iter_points", "`pipeline.reading.iter_points` (checks + local frame)")):
            out.append(f"| {label} | {_mpts(d[key]['points_per_s'])} | {st['points_per_s'] / d[key]['points_per_s']:.3f} |")
        out += ["", "![stages](stages.png)"]

    sc = data.get("scaling")
    if sc:
        out += ["", "## Throughput and memory against block size", ""]
        out.append(f"Generated orchard blocks at the stand's point density, tiled ({sc['tile_size']:g} m tiles, buffer = "
                   f"`params.reach()`), {sc['workers']} single-threaded dask worker processes of a `LocalCluster`, LAZ in → Parquet out. "
                   "Memory of every process of the job: the *submitting process* (it reads the header, tiles, merges and writes; "
                   "the `LocalCluster` runs its scheduler and the workers' nannies in this process, so there is no scheduler "
                   "process of its own) and *each worker* process, by their own high-water mark (VmHWM, read in each process "
                   "at the end); *other processes* (multiprocessing's resource tracker) by their largest RSS sampled every "
                   "0.1 s; *all processes* is the largest sum over the process tree at one sample.")
        out += ["", "| points | trees (found) | tiles | wall time | CPU time | cores used | points/s | submitting process | each worker | other processes | all processes | LAZ decode (x/y/z) | end-to-end ÷ decode |",
                "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in sc["rows"]:
            out.append(f"| {r['n_points']:,} | {r['n_trees']} ({r['n_found']}) | {r['n_tiles']} | {r['wall_s']:.1f} s | {r.get('cpu_s', float('nan')):.1f} s | {_cores(r)} | {_mpts(r['points_per_s'])} | "
                       f"{_gib(r['main_maxrss'])} | {_each_gib(r['worker_maxrss'])} | {_other_processes(r.get('sampled_peaks'))} | {_gib(r['tree_peak_total'])} | "
                       f"{_mpts(r['decode']['laspy_xyz_only']['points_per_s'])} | {r['ratio_vs_decode']:.3f} |")
        out += ["", f"Fitted scaling exponent (least squares of log time on log points): **{_f(sc['exponent'])}** "
                "(1 = linear).", "", "![scaling](scaling.png)"]
        for note in data.get("scaling_notes") or ([data["skipped_50m"]] if data.get("skipped_50m") else []):
            out += ["", f"_{note}_"]

    wk = data.get("workers")
    if wk:
        b = wk["block"]
        out += ["", "## 1 versus 2 workers", ""]
        out.append(f"The same block ({b['n_points']:,} points, {b['n_trees']} trees), tiled ({wk['tile_size']:g} m), "
                   "on a fresh `LocalCluster` of single-threaded worker processes:")
        out += ["", "| workers | wall time | CPU time | cores used (CPU ÷ wall) | speed-up | tiles | tiling / processing / merge+write | largest worker peak |",
                "| --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in wk["rows"]:
            out.append(f"| {r['workers']} | {r['wall_s']:.1f} s | {r.get('cpu_s', float('nan')):.1f} s | {_cores(r)} | "
                       f"{r['speedup']:.2f}× | {r['n_tiles']} | {_stage_split(r)} | {_gib(max(r['worker_maxrss'] or [0]))} |")
        two = [r for r in wk["rows"] if r["workers"] >= 2 and r.get("cpu_s")]
        if two and two[0]["cpu_s"] / two[0]["wall_s"] < 1.5:
            out += ["", f"With {two[0]['workers']} workers the measured processes used only "
                    f"{two[0]['cpu_s'] / two[0]['wall_s']:.2f} cores on average: other processes held the rest of this "
                    "shared machine's CPU, so this run cannot show the speed-up that idle cores would give; the CPU "
                    "time of both runs (the same work) is the figure to compare."]
        if data["machine"]["usable_cores"] <= 2:
            out += ["", f"This machine has {data['machine']['usable_cores']} cores, shared by the workers and the "
                    "process that tiles, merges and writes."]

    ts = data.get("tiles")
    if ts:
        b = ts["block"]
        out += ["", "## Tile size", ""]
        out.append(f"The same block ({b['n_points']:,} points, {b['n_trees']} trees) at several tile sizes, on a fresh "
                   f"`LocalCluster` of {ts['workers']} single-threaded worker processes. Each tile is processed with a "
                   f"{ts['buffer']:.2f} m buffer on every side (`params.reach()`), so an interior tile of size s "
                   "processes ((s + 2 × buffer) / s)² times the points of its core (*buffer factor*): larger tiles "
                   "repeat less work and need more memory per worker.")
        out += ["", "| tile size | buffer factor | tiles | trees found | wall time | CPU time | points/s | tiling / processing / merge+write | largest worker peak |",
                "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        for r in ts["rows"]:
            out.append(f"| {r['tile_size']:g} m | {r['buffer_factor']:.2f} | {r['n_tiles']} | {r['n_found']} | "
                       f"{r['wall_s']:.1f} s | {r.get('cpu_s', float('nan')):.1f} s | {_mpts(r['points_per_s'])} | {_stage_split(r)} | "
                       f"{_gib(max(r['worker_maxrss'] or [0]))} |")

    pe = data.get("peers")
    if pe:
        st = pe["status"]
        out += ["", "## Peers from PyPI", ""]
        out.append(f"**{st['peer']}** (the library behind 3DFin): `pip download --no-deps {st['peer']}`: {st.get('download', '–')}; "
                   f"installed into its own virtualenv (it pins laspy ~2.5.4 and scipy < 1.17): {st.get('install', 'not attempted')}"
                   + (f" ({', '.join(f'{k} {v}' for k, v in st['versions'].items())})" if st.get("versions") else "") + ".")
        if pe.get("runs"):
            out.append("")
            out.append("Its tree individualisation (cloth-simulation DTM → stem stripe → verticality clustering → "
                       "distance to stem axes, following 3DFin's standard processing) on the same generated block, "
                       "scored with the same evaluator. It has no wood/leaf classification.")
            out += ["", "| method | block | trees true / found | trunk F1 | v-measure | wood F1 | seconds |", "| --- | --- | --- | --- | --- | --- | --- |"]
            for run in pe["runs"]:
                v = run["metrics"]
                if "error" in v:
                    out.append(f"| {run['method']} | {run['block']} | – | error: {_cell(v['error'])} | | | |")
                else:
                    out.append(f"| {run['method']} | {run['block']} | {v.get('n_true_trees', '–')} / {v.get('n_found_trees', '–')} | "
                               f"{_f(v['trunk_f1'])} | {_f(v['v_measure'])} | {_f(v.get('wood_f1'))} | {_f(v.get('seconds'), 1)} |")
        if pe.get("note"):
            out += ["", pe["note"]]
    out.append("")
    return "\n".join(out)


def splice_section(page: Path, results_md: str, *, image_prefix: str = "../bench/") -> bool:
    """Replace the text of ``page`` between the bench markers with ``results_md``.

    The results' title is dropped and their headings are nested under the page's last
    heading above the start marker; relative image links get ``image_prefix`` (the plots
    live in ``bench/``, the page in ``docs/``). Returns False, writing nothing, when the
    page or its markers are missing.
    """
    if not page.exists():
        return False
    text = page.read_text()
    if START not in text or END not in text or text.index(START) > text.index(END):
        return False
    above = re.findall(r"^(#+) ", text[: text.index(START)], flags=re.M)
    level = len(above[-1]) if above else 1
    body = re.sub(r"\A# [^\n]*\n+", "", results_md)
    body = re.sub(r"^(#+) ", lambda mm: "#" * (len(mm.group(1)) + level - 1) + " ", body, flags=re.M)
    body = re.sub(r"!\[([^\]]*)\]\((?!https?:|/)([^)]+)\)", lambda mm: f"![{mm.group(1)}]({image_prefix}{mm.group(2)})", body)
    a = text.index(START) + len(START)
    b = text.index(END)
    page.write_text(text[:a] + "\n" + body.strip() + "\n" + text[b:])
    return True
