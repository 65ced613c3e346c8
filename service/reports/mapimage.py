"""The report's map as a PNG: matplotlib axes, the points drawn into one image.

The block from above in the local frame [m]: points not in a tree light grey, tree points
in a colour of their tree id, each trunk a white disc with a black edge and its number.
Hundreds of thousands of points as scatter markers cost matplotlib about a second to
draw; as one-pixel dots composed with numpy into an image the axes show, they cost a
few hundredths, and matplotlib still draws the frame, ticks, labels and markers.
"""

from __future__ import annotations

import io

import numpy as np

DPI = 100
"""Pixels per inch of the map."""

WIDTH_IN = 10.0
"""Width of the map [in]."""

#: tab20 without its two greys (14, 15): grey is "not a tree" (RGB, 0-1)
PALETTE = np.array([
    (31, 119, 180), (174, 199, 232), (255, 127, 14), (255, 187, 120), (44, 160, 44), (152, 223, 138),
    (214, 39, 40), (255, 152, 150), (148, 103, 189), (197, 176, 213), (140, 86, 75), (196, 156, 148),
    (227, 119, 194), (247, 182, 210), (188, 189, 34), (219, 219, 141), (23, 190, 207), (158, 218, 229),
], dtype=np.float32) / 255.0

OTHER = np.array((200, 200, 200), dtype=np.float32) / 255.0
"""Colour of the points outside every tree (#c8c8c8)."""

# opacity of one point's one-pixel dot, near the grey and colour density of the
# anti-aliased scatter markers of 0.3 and 0.6 pt² the map used to draw
OTHER_COVER = 0.7
TREE_COVER = 0.9

MARGIN = 0.05
"""Space left around the data, as a share of its extent on each axis."""


def blend_dots(canvas: np.ndarray, col: np.ndarray, row: np.ndarray, colours: np.ndarray, cover: float) -> None:
    """Points as one-pixel dots of coverage ``cover`` on an (h, w, 3) float image, the
    later on top, ``k`` dots in one pixel covering ``1 - (1 - cover)^k`` of it (in place)."""
    h, w, _ = canvas.shape
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    flat = (row[inside] * w + col[inside]).astype(np.int64)
    colours = colours[inside]
    if not len(flat):
        return
    order = np.argsort(flat, kind="stable")
    flat, colours = flat[order], colours[order]
    last = np.r_[flat[1:] != flat[:-1], True]
    counts = np.diff(np.r_[-1, np.nonzero(last)[0]])
    alpha = (1.0 - (1.0 - cover) ** counts)[:, None].astype(np.float32)
    px = canvas.reshape(-1, 3)
    px[flat[last]] = px[flat[last]] * (1.0 - alpha) + colours[last] * alpha


def point_image(xy: np.ndarray, tree_id: np.ndarray, lo: np.ndarray, hi: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width, 3) float32 RGB image of the points on white over the box
    ``lo``..``hi`` [m] (row 0 at ``hi[1]``)."""
    canvas = np.ones((height, width, 3), np.float32)
    col = np.floor((xy[:, 0] - lo[0]) / (hi[0] - lo[0]) * width).astype(np.int64)
    row = np.floor((hi[1] - xy[:, 1]) / (hi[1] - lo[1]) * height).astype(np.int64)
    other = np.asarray(tree_id) <= 0
    blend_dots(canvas, col[other], row[other], np.broadcast_to(OTHER, (int(other.sum()), 3)), OTHER_COVER)
    trees = ~other
    blend_dots(canvas, col[trees], row[trees], PALETTE[(np.asarray(tree_id)[trees] * 7) % len(PALETTE)], TREE_COVER)
    return canvas


def render_map_png(
    xy: np.ndarray, tree_id: np.ndarray, trunks_xy: np.ndarray, trunk_ids: np.ndarray, *, title: str
) -> bytes:
    """PNG of the block from above: tree points coloured by id, trunk markers with numbers.

    Parameters
    ----------
    xy : (n, 2) float
        Points [m], local frame.
    tree_id : (n,) int
        Tree of each point; 0 or less is no tree.
    trunks_xy : (t, 2) float
        Trunks [m], same frame as ``xy``.
    trunk_ids : (t,) int
        Number written beside each trunk.
    title : str
        Drawn as text ("$" is no formula).
    """
    # here: matplotlib (~1-2 s) loads with the first map drawn, not with the server or `orchard process --help`
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    trunks_xy = np.asarray(trunks_xy, dtype=np.float64).reshape(-1, 2)
    pts = np.vstack([xy, trunks_xy]) if len(trunks_xy) else xy
    if len(pts):
        lo, hi = pts.min(axis=0), pts.max(axis=0)
    else:
        lo, hi = np.zeros(2), np.ones(2)
    span = np.maximum(hi - lo, 1.0)
    height_in = float(np.clip(WIDTH_IN * span[1] / span[0], 3.0, 14.0))
    flat = hi - lo <= 0
    lo, hi = np.where(flat, lo - 1.0, lo), np.where(flat, hi + 1.0, hi)
    lo, hi = lo - MARGIN * (hi - lo), hi + MARGIN * (hi - lo)

    fig = Figure(figsize=(WIDTH_IN, height_in + 0.8), dpi=DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (local)")
    ax.set_ylabel("y [m] (local)")
    ax.set_title(title, parse_math=False)  # a file name with "$...$" is text, not a formula
    fig.tight_layout()
    # no layout engine left behind: with tight_layout's placeholder, savefig draws the
    # whole figure once more to lay it out (about a quarter of the map's cost), for a
    # layout that is already done
    fig.set_layout_engine(None)
    ax.apply_aspect()
    box = ax.get_position()  # the axes after the equal aspect, in figure fractions
    width = max(int(round(box.width * fig.bbox.width)), 1)
    height = max(int(round(box.height * fig.bbox.height)), 1)
    ax.imshow(point_image(xy, tree_id, lo, hi, width, height), extent=(lo[0], hi[0], lo[1], hi[1]),
              origin="upper", interpolation="nearest", aspect="equal", zorder=1)
    if len(trunks_xy):
        ax.scatter(trunks_xy[:, 0], trunks_xy[:, 1], s=40, marker="o", facecolors="white", edgecolors="black",
                   linewidths=1.2, zorder=3)
        for (x, y), k in zip(trunks_xy, trunk_ids):
            ax.annotate(str(int(k)), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=9,
                        fontweight="bold", zorder=4)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()
