"""PNG charts of the static HTML report, drawn with matplotlib's object API on the Agg canvas.

Figures are made with `matplotlib.figure.Figure` directly, never through pyplot: no global figure registry, no
interactive backend, nothing to close, safe in worker threads (they take turns: `_fonts`). Every function returns
PNG bytes.

Text is set in matplotlib's DejaVu Sans, and each glyph it lacks (Chinese, Japanese, Korean: an utterance id such as
`普通话/0001`) is taken from the first CJK font the machine has (`font_families`; `make` installs Debian's
`fonts-droid-fallback`). Without one such glyphs draw as empty boxes, as matplotlib warns.
"""

import functools
import io
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import matplotlib
import numpy as np
from matplotlib import font_manager
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from PIL import Image  # a dependency of matplotlib

from visemeflow.visemes import VISEMES

DPI = 90
WIDTH_IN = 14.0
# One colour per viseme, the same in every chart: tab20 has 20 distinct colours.
_TAB20 = (
    "#1f77b4", "#aec7e8", "#ff7f0e", "#ffbb78", "#2ca02c", "#98df8a", "#d62728", "#ff9896",
    "#9467bd", "#c5b0d5", "#8c564b", "#c49c94", "#e377c2", "#f7b6d2", "#7f7f7f", "#c7c7c7",
)
VISEME_COLOURS = dict(zip(VISEMES, _TAB20))
# Samples drawn per waveform: a min/max envelope over this many columns looks like the full signal.
ENVELOPE_COLUMNS = 2400


# CJK fonts by family name (as Windows, macOS and Linux desktops name theirs), then by file where Debian puts them
# (a font installed after matplotlib built its font list is not in it: these are added by path)
CJK_FAMILIES = ("Noto Sans CJK SC", "Noto Sans CJK JP", "Source Han Sans SC", "Microsoft YaHei", "PingFang SC",
                "Hiragino Sans", "WenQuanYi Micro Hei", "WenQuanYi Zen Hei", "Droid Sans Fallback")
CJK_FONT_FILES = ("/usr/share/fonts/truetype/droid/DroidSansFallbackFull.ttf",
                  "/usr/share/fonts/opentype/noto/NotoSansCJK-Regular.ttc",
                  "/usr/share/fonts/truetype/wqy/wqy-microhei.ttc",
                  "/usr/share/fonts/truetype/wqy/wqy-zenhei.ttc")
_F = TypeVar("_F", bound=Callable[..., Any])


@functools.cache
def font_families() -> tuple[str, ...]:
    """DejaVu Sans, then the CJK fonts found (`CJK_FAMILIES`, `CJK_FONT_FILES`): matplotlib draws each glyph in the
    first of them that has it."""
    known = {f.name for f in font_manager.fontManager.ttflist}
    files = {f.fname for f in font_manager.fontManager.ttflist}
    for path in CJK_FONT_FILES:
        if path not in files and Path(path).is_file():
            try:
                font_manager.fontManager.addfont(path)
            except (OSError, RuntimeError, ValueError):   # unreadable: that font is not used
                continue
            known = {f.name for f in font_manager.fontManager.ttflist}
    return ("DejaVu Sans",) + tuple(name for name in CJK_FAMILIES if name in known)


_RC_LOCK = threading.Lock()   # rc_context saves and restores matplotlib's global rcParams: one figure at a time


def _fonts(draw: _F) -> _F:
    """Draw with `font_families()` (matplotlib's text takes its font when made, so the whole figure is inside);
    figures drawn in several threads take turns, since the font setting is global while it lasts."""
    @functools.wraps(draw)
    def drawn(*args: Any, **kwargs: Any) -> Any:
        with _RC_LOCK, matplotlib.rc_context({"font.family": list(font_families())}):
            return draw(*args, **kwargs)
    return drawn  # type: ignore[return-value]


def plain(text: object) -> str:
    """`text` for a matplotlib label: a `$` would start mathtext (and may fail to parse), so escape it."""
    return str(text).replace("$", r"\$")


def _png(fig: Figure) -> bytes:
    """The figure as a 256-colour PNG: charts of flat colours lose nothing visible and shrink 2-3 times."""
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    image = Image.open(io.BytesIO(buf.getvalue())).convert("RGB").quantize(256, method=Image.Quantize.FASTOCTREE)
    out = io.BytesIO()
    image.save(out, format="PNG")
    return out.getvalue()


def _panel_label(label: str, width: int = 16) -> str:
    """A panel's y label: each line wrapped at `width` characters, after a '-' or '_' where possible."""
    lines = []
    for line in label.split("\n"):
        while len(line) > width:
            cut = max(line.rfind("-", 0, width), line.rfind("_", 0, width))
            cut = cut + 1 if cut > 0 else width
            lines.append(line[:cut])
            line = line[cut:]
        lines.append(line)
    return "\n".join(lines)


@dataclass(frozen=True)
class Phone:
    start_s: float
    end_s: float
    label: str
    silent: bool  # no viseme (silence, transparent phones)


@dataclass(frozen=True)
class CurvePanel:
    label: str             # e.g. "tracked\nguided-fast"
    time_s: np.ndarray     # (frames,)
    curves: np.ndarray     # (frames, 16)


def envelope(samples: np.ndarray, columns: int = ENVELOPE_COLUMNS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(column index, min, max) of `samples` over `columns` equal blocks: a long recording drawn in constant time."""
    samples = np.asarray(samples, dtype=np.float32).reshape(-1)
    n = samples.size
    if n <= 2 * columns:
        idx = np.arange(n, dtype=np.float64)
        return idx, samples, samples
    edges = np.linspace(0, n, columns + 1).astype(np.int64)
    lo = np.minimum.reduceat(samples, edges[:-1])
    hi = np.maximum.reduceat(samples, edges[:-1])
    return edges[:-1].astype(np.float64), lo, hi


@_fonts
def utterance_figure(
    title: str,
    duration_s: float,
    waveform: tuple[np.ndarray, int] | None,
    waveform_note: str,
    phones: Sequence[Phone],
    panels: Sequence[CurvePanel],
) -> bytes:
    """Waveform, phone labels and one panel of 16 viseme curves per (source, variant), on one time axis."""
    n_panels = max(len(panels), 1)
    heights = [1.0, 0.6] + [1.6] * n_panels
    fig = Figure(figsize=(WIDTH_IN, 0.9 * sum(heights) + 0.9))
    axes = fig.subplots(len(heights), 1, sharex=True, gridspec_kw={"height_ratios": heights, "hspace": 0.08})
    fig.subplots_adjust(left=0.1, right=0.9, top=1 - 0.35 / fig.get_figheight(), bottom=0.55 / fig.get_figheight())
    fig.suptitle(plain(title), x=0.1, ha="left", fontsize=11)
    end = max(duration_s, max((float(p.time_s[-1]) for p in panels if len(p.time_s)), default=0.0),
              max((ph.end_s for ph in phones), default=0.0), 1e-3)

    ax = axes[0]
    if waveform is not None:
        samples, rate = waveform
        idx, lo, hi = envelope(samples)
        t = idx / float(rate)
        ax.fill_between(t, lo, hi, color="#555555", linewidth=0.6, step="post")
        peak = float(max(np.abs(lo).max(initial=0.0), np.abs(hi).max(initial=0.0), 1e-6))
        ax.set_ylim(-peak * 1.05, peak * 1.05)
        end = max(end, samples.shape[0] / float(rate))
    else:
        ax.text(0.5, 0.5, plain(waveform_note), transform=ax.transAxes, ha="center", va="center", color="#a33")
    ax.set_yticks([])
    ax.set_ylabel("audio", rotation=0, ha="right", va="center")

    ax = axes[1]
    for k, ph in enumerate(phones):
        ax.axvspan(ph.start_s, ph.end_s, color="#eeeeee" if k % 2 else "#dde6f0", linewidth=0)
        # Three rows of labels, so that short neighbouring phones do not print over each other.
        ax.text((ph.start_s + ph.end_s) / 2, 0.8 - 0.3 * (k % 3), plain(ph.label), ha="center", va="center",
                fontsize=7, color="#999999" if ph.silent else "#000000", clip_on=True)
    if not phones:
        ax.text(0.5, 0.5, "no phones stored", transform=ax.transAxes, ha="center", va="center", color="#a33")
    ax.set_ylim(0, 1)
    ax.set_yticks([])
    ax.set_ylabel("phones", rotation=0, ha="right", va="center")

    boundaries = sorted({ph.start_s for ph in phones} | {ph.end_s for ph in phones})
    lines = []
    for ax, panel in zip(axes[2:], panels):
        for b in boundaries:
            ax.axvline(b, color="#e4e4e4", linewidth=0.6, zorder=0)
        for i, v in enumerate(VISEMES):
            (line,) = ax.plot(panel.time_s, panel.curves[:, i], color=VISEME_COLOURS[v], linewidth=1.2, label=v)
            if len(lines) < len(VISEMES):
                lines.append(line)
        ax.set_ylim(-0.03, 1.05)
        ax.set_yticks([0, 0.5, 1])
        ax.set_ylabel(plain(_panel_label(panel.label)), rotation=0, ha="right", va="center", fontsize=8)
    if not panels:
        axes[2].text(0.5, 0.5, "no curves stored", transform=axes[2].transAxes, ha="center", va="center", color="#a33")
        axes[2].set_yticks([])
    if lines:
        fig.legend(lines, VISEMES, loc="center right", fontsize=8, frameon=False, bbox_to_anchor=(0.995, 0.5))
    axes[-1].set_xlim(0, end)
    axes[-1].set_xlabel("time (s)")
    return _png(fig)


@_fonts
def histogram_figure(errors: dict[str, np.ndarray], xlabel: str) -> bytes:
    """Overlaid histograms (density) of one value per variant, on shared bins, with each median marked."""
    fig = Figure(figsize=(9.0, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    values = [v for v in errors.values() if v.size]
    top = float(np.percentile(np.concatenate(values), 99.5)) if values else 1.0
    bins = np.linspace(0.0, max(top, 1e-6), 50)
    for k, (variant, v) in enumerate(errors.items()):
        colour = _TAB20[(2 * k) % len(_TAB20)]
        if not v.size:
            continue
        median = float(np.median(v))
        ax.hist(np.clip(v, 0, bins[-1]), bins=bins, density=True, histtype="stepfilled", alpha=0.35, color=colour,
                label=plain(f"{variant} (median {median:.2f}, {v.size} frames)"))
        ax.axvline(median, color=colour, linestyle="--", linewidth=1)
    ax.set_xlabel(plain(xlabel))
    ax.set_ylabel("density")
    ax.legend(fontsize=8, frameon=False)
    fig.tight_layout()
    return _png(fig)


@_fonts
def training_figure(series: dict[str, tuple[np.ndarray, np.ndarray]]) -> bytes:
    """Validation L1 x 100 by epoch, one line per model."""
    fig = Figure(figsize=(9.0, 3.6))
    ax = fig.add_subplot(1, 1, 1)
    for k, (name, (epochs, values)) in enumerate(series.items()):
        ax.plot(epochs, values, marker="o", markersize=3, color=_TAB20[(2 * k) % len(_TAB20)], label=plain(name))
    ax.set_xlabel("epoch")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("validation L1 x 100")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, frameon=False)
    fig.tight_layout()
    return _png(fig)


@_fonts
def sweep_figure(points: Sequence[tuple[int, float]], title: str) -> bytes:
    """Paper Fig. 5: validation L1 x 100 against the number of training utterances (log x axis), each point labelled."""
    fig = Figure(figsize=(7.2, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    sizes = [int(size) for size, _ in points]
    values = [float(value) for _, value in points]
    ax.plot(sizes, values, marker="o", markersize=6, linewidth=2, color=_TAB20[0])
    for size, value in zip(sizes, values):
        ax.annotate(f"{value:.2f}", (size, value), textcoords="offset points", xytext=(6, 6), fontsize=9)
    ax.set_xscale("log")
    ax.set_xticks(sizes, [str(s) for s in sizes])
    ax.minorticks_off()
    if sizes:
        lo, hi = min(sizes), max(sizes)
        ax.set_xlim(lo / 1.25, hi * 1.25)
    ax.set_ylim(0.0, max([*values, 1e-6]) * 1.15)
    ax.set_xlabel("training utterances (log scale)")
    ax.set_ylabel("validation L1 x 100")
    ax.set_title(plain(title), fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return _png(fig)
