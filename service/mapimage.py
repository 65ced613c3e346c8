"""The report's map as a PNG, drawn with numpy and Pillow.

The block from above in the local frame [m]: points not in a tree light grey, tree points
in a colour of their tree id, each trunk a white disc with a black edge and its number, a
framed plot with ticks, axis labels and a title. The layout follows the matplotlib figure
the report used to draw (10 in wide at 100 dpi, equal aspect, 5 % margins around the
data, tab20 colours without its greys, DejaVu Sans), so the map reads the same; drawn
here, a run never imports matplotlib, whose import and drawing of a few hundred thousand
markers were the report's main cost.
"""

from __future__ import annotations

import importlib.util
import io
import math
from functools import lru_cache
from pathlib import Path

import numpy as np

DPI = 100
"""Pixels per inch of the map."""

WIDTH_IN = 10.0
"""Width of the map [in]."""

#: tab20 without its two greys (14, 15): grey is "not a tree" (RGB, 0-255)
PALETTE = np.array([
    (31, 119, 180), (174, 199, 232), (255, 127, 14), (255, 187, 120), (44, 160, 44), (152, 223, 138),
    (214, 39, 40), (255, 152, 150), (148, 103, 189), (197, 176, 213), (140, 86, 75), (196, 156, 148),
    (227, 119, 194), (247, 182, 210), (188, 189, 34), (219, 219, 141), (23, 190, 207), (158, 218, 229),
], dtype=np.float32) / 255.0

OTHER = np.array((200, 200, 200), dtype=np.float32) / 255.0
"""Colour of the points outside every tree (#c8c8c8)."""

# opacity of one point's one-pixel dot, matched to the grey and colour density of
# matplotlib's anti-aliased markers of 0.3 and 0.6 pt² (0.76 and 1.08 px wide)
OTHER_COVER = 0.7
TREE_COVER = 0.9

MARGIN = 0.05
"""Space left around the data, as a share of its extent on each axis."""


def _px(points: float) -> float:
    """Typographic points → pixels."""
    return points * DPI / 72.0


@lru_cache(maxsize=None)
def _font(size_pt: float, bold: bool = False):
    from PIL import ImageFont

    name = "DejaVuSans-Bold.ttf" if bold else "DejaVuSans.ttf"
    # matplotlib ships DejaVu Sans: found without importing matplotlib
    spec = importlib.util.find_spec("matplotlib")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        path = Path(folder) / "mpl-data" / "fonts" / "ttf" / name
        if path.is_file():
            return ImageFont.truetype(str(path), _px(size_pt))
    try:
        return ImageFont.truetype(name, _px(size_pt))
    except OSError:
        return ImageFont.load_default(_px(size_pt))


def nice_ticks(lo: float, hi: float, nbins: int) -> np.ndarray:
    """At most ``nbins`` + 1 round tick values (steps of 1, 2, 2.5 or 5 × 10ⁿ) in [lo, hi]."""
    span = hi - lo
    if not span > 0:
        return np.array([lo])
    scale = 10.0 ** math.floor(math.log10(span / nbins))
    steps = np.array([1.0, 2.0, 2.5, 5.0, 10.0]) * scale
    first = int(np.nonzero(steps >= span / nbins * (1 - 1e-9))[0][0])
    for step in steps[: first + 1][::-1]:  # a smaller step when the larger leaves fewer than two ticks
        ticks = np.arange(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1) * step
        if len(ticks) >= 2:
            break
    return ticks


def tick_labels(ticks: np.ndarray) -> list[str]:
    """Tick values with the fewest decimals that tell them apart, minus as U+2212."""
    decimals = 0
    while decimals < 6 and not np.allclose(np.round(ticks, decimals), ticks, rtol=0, atol=1e-9):
        decimals += 1
    return [f"{0.0 if abs(t) < 1e-12 else t:.{decimals}f}".replace("-", "\u2212") for t in ticks]


def _limits(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(pts):
        lo, hi = pts.min(axis=0).astype(np.float64), pts.max(axis=0).astype(np.float64)
    else:
        lo, hi = np.zeros(2), np.ones(2)
    flat = hi - lo <= 0
    lo, hi = np.where(flat, lo - 1.0, lo), np.where(flat, hi + 1.0, hi)
    pad = MARGIN * (hi - lo)
    return lo - pad, hi + pad


def _text_size(font, text: str) -> tuple[float, float]:
    left, top, right, bottom = font.getbbox(text)
    return right - left, bottom - top


def _layout(width: int, height: int, lo: np.ndarray, hi: np.ndarray, title: str) -> dict:
    """The axes' box [px] and ticks: margins fitted to the labels, then the box shrunk to
    an equal aspect, centred."""
    f10, f12 = _font(10.0), _font(12.0)
    pad, tick_len, tick_pad, label_pad = _px(10.8), _px(3.5), _px(3.5), _px(4.0)
    label_h = _text_size(f10, "x [m] (local)")[1]
    digit_h = _text_size(f10, "0123456789")[1]
    title_h = _text_size(f12, title or "x")[1]
    top = pad + title_h + _px(6.0)
    bottom = pad + label_h + label_pad + digit_h + tick_pad + tick_len
    left, right = pad + 60.0, pad
    ratio = (hi[1] - lo[1]) / (hi[0] - lo[0])

    def fit(left: float, right: float) -> tuple[float, float, float, float]:
        # the subplot area within the margins, shrunk to an equal aspect, centred
        box_l, box_t, box_w, box_h = left, top, width - left - right, height - top - bottom
        if box_h > box_w * ratio:
            box_t += (box_h - box_w * ratio) / 2
            box_h = box_w * ratio
        else:
            box_l += (box_w - box_h / ratio) / 2
            box_w = box_h / ratio
        return box_l, box_t, box_w, box_h

    for _ in range(3):  # ticks follow the box's size, the margins the ticks' labels
        box_l, box_t, box_w, box_h = fit(left, right)
        xt = nice_ticks(lo[0], hi[0], int(np.clip(math.floor(box_w * 72 / DPI / 30.0), 1, 9)))
        yt = nice_ticks(lo[1], hi[1], int(np.clip(math.floor(box_h * 72 / DPI / 20.0), 1, 9)))
        y_w = max(_text_size(f10, s)[0] for s in tick_labels(yt))
        left = pad + label_h + label_pad + y_w + tick_pad + tick_len
        # the last x tick label may reach past the box's right edge
        x_over = _text_size(f10, tick_labels(xt)[-1])[0] / 2 - box_w * (hi[0] - xt[-1]) / (hi[0] - lo[0])
        right = pad + max(0.0, x_over)
    box_l, box_t, box_w, box_h = fit(left, right)
    left, top = box_l, box_t
    return dict(left=left, top=top, w=box_w, h=box_h, xticks=xt, yticks=yt, y_label_w=y_w, digit_h=digit_h,
                tick_len=tick_len, tick_pad=tick_pad, label_pad=label_pad)


def _blend_dots(canvas: np.ndarray, col: np.ndarray, row: np.ndarray, colours: np.ndarray, cover: float) -> None:
    """Points as one-pixel dots of coverage ``cover``, the later on top (in place)."""
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


def _disc(canvas: np.ndarray, cx: float, cy: float, *, diameter: float, edge: float, sub: int = 6) -> None:
    """A white disc with a black edge, anti-aliased by supersampling (in place)."""
    h, w, _ = canvas.shape
    outer, inner = diameter / 2 + edge / 2, diameter / 2 - edge / 2
    x0, x1 = max(int(math.floor(cx - outer)), 0), min(int(math.ceil(cx + outer)) + 1, w)
    y0, y1 = max(int(math.floor(cy - outer)), 0), min(int(math.ceil(cy + outer)) + 1, h)
    if x0 >= x1 or y0 >= y1:
        return
    offs = (np.arange(sub) + 0.5) / sub
    xs = (np.arange(x0, x1)[:, None] + offs[None, :]).ravel() - cx
    ys = (np.arange(y0, y1)[:, None] + offs[None, :]).ravel() - cy
    r = np.hypot(xs[None, :], ys[:, None]).reshape(y1 - y0, sub, x1 - x0, sub)
    white = (r <= inner).mean(axis=(1, 3))[..., None]
    black = ((r > inner) & (r <= outer)).mean(axis=(1, 3))[..., None]
    patch = canvas[y0:y1, x0:x1]
    canvas[y0:y1, x0:x1] = patch * (1.0 - white - black) + white


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
    from PIL import Image, ImageDraw

    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    trunks_xy = np.asarray(trunks_xy, dtype=np.float64).reshape(-1, 2)
    pts = np.vstack([xy, trunks_xy]) if len(trunks_xy) else xy
    span = np.maximum(pts.max(axis=0) - pts.min(axis=0), 1.0) if len(pts) else np.ones(2)
    height_in = float(np.clip(WIDTH_IN * span[1] / span[0], 3.0, 14.0)) + 0.8
    width, height = int(WIDTH_IN * DPI), int(height_in * DPI)  # as matplotlib sizes a figure
    lo, hi = _limits(pts)
    box = _layout(width, height, lo, hi, title)

    def to_px(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (box["left"] + (p[:, 0] - lo[0]) / (hi[0] - lo[0]) * box["w"],
                box["top"] + (hi[1] - p[:, 1]) / (hi[1] - lo[1]) * box["h"])

    canvas = np.ones((height, width, 3), np.float32)
    px, py = to_px(xy)
    col, row = np.floor(px).astype(np.int64), np.floor(py).astype(np.int64)
    other = np.asarray(tree_id) <= 0
    _blend_dots(canvas, col[other], row[other], np.broadcast_to(OTHER, (int(other.sum()), 3)), OTHER_COVER)
    trees = ~other
    colours = PALETTE[(np.asarray(tree_id)[trees] * 7) % len(PALETTE)]
    _blend_dots(canvas, col[trees], row[trees], colours, TREE_COVER)
    tx, ty = to_px(trunks_xy)
    for x, y in zip(tx, ty):
        _disc(canvas, x, y, diameter=_px(math.sqrt(40.0)), edge=_px(1.2))

    image = Image.fromarray(np.round(canvas * 255).astype(np.uint8), "RGB")
    draw = ImageDraw.Draw(image)
    f9b, f10, f12 = _font(9.0, bold=True), _font(10.0), _font(12.0)
    for (x, y), k in zip(zip(tx, ty), trunk_ids):
        draw.text((x + _px(4.0), y - _px(4.0)), str(int(k)), fill="black", font=f9b, anchor="ls")
    left, top, right, bottom = box["left"], box["top"], box["left"] + box["w"], box["top"] + box["h"]
    draw.rectangle([round(left), round(top), round(right), round(bottom)], outline="black", width=1)
    tl, tp = box["tick_len"], box["tick_pad"]
    for t, s in zip(box["xticks"], tick_labels(box["xticks"])):
        x = round(left + (t - lo[0]) / (hi[0] - lo[0]) * box["w"])
        draw.line([(x, round(bottom)), (x, round(bottom + tl))], fill="black", width=1)
        draw.text((x, bottom + tl + tp), s, fill="black", font=f10, anchor="mt")
    for t, s in zip(box["yticks"], tick_labels(box["yticks"])):
        y = round(top + (hi[1] - t) / (hi[1] - lo[1]) * box["h"])
        draw.line([(round(left - tl), y), (round(left), y)], fill="black", width=1)
        draw.text((left - tl - tp, y), s, fill="black", font=f10, anchor="rm")
    label_top = bottom + tl + tp + box["digit_h"] + box["label_pad"]
    draw.text(((left + right) / 2, label_top), "x [m] (local)", fill="black", font=f10, anchor="mt")
    draw.text(((left + right) / 2, top - _px(6.0)), title, fill="black", font=f12, anchor="ms")
    ylabel = "y [m] (local)"
    w, h = _text_size(f10, ylabel)
    strip = Image.new("L", (int(math.ceil(w)) + 4, int(math.ceil(h)) + 6), 0)
    ImageDraw.Draw(strip).text((2, 3), ylabel, fill=255, font=f10, anchor="lt")
    strip = strip.rotate(90, expand=True)
    x = left - tl - tp - box["y_label_w"] - box["label_pad"] - strip.width
    image.paste((0, 0, 0), (int(round(x)), int(round((top + bottom) / 2 - strip.height / 2))), strip)
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    return buf.getvalue()
