"""One look for every figure: colour-blind-safe palettes, one colour per layer, frame axes in engineering notation."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
from matplotlib.axes import Axes
from matplotlib.ticker import EngFormatter

from sb3_collapse.common.layers import LAYER_NAMES

OKABE_ITO = ("#E69F00", "#56B4E9", "#009E73", "#0072B2", "#D55E00", "#CC79A7", "#F0E442", "#000000")
"""The eight colours of Okabe & Ito (orange, sky blue, bluish green, blue, vermillion, reddish purple, yellow, black),
distinguishable with the common colour-vision deficiencies."""
TOL_MUTED = ("#332288", "#88CCEE", "#44AA99", "#117733", "#999933", "#DDCC77", "#CC6677", "#882255", "#AA4499")
"""Paul Tol's colour-blind-safe "muted" scheme: more colours once Okabe-Ito's are used."""

_LAYER_COLOR_LIST = ("#000000", "#56B4E9", "#009E73", "#F0E442", "#D55E00", "#CC79A7", "#0072B2", "#E69F00", "#777777")
LAYER_COLORS: dict[str, str] = dict(zip(LAYER_NAMES, _LAYER_COLOR_LIST))
"""Layer -> its colour in every figure (``cnn0``, the pixels, black)."""

RETURN_COLOR = "#000000"
"""The evaluation return's colour."""
RESET_COLOR = "#666666"
"""Vertical lines at the resets of the reset rule."""
ESCAPE_COLOR = "#009E73"
"""Vertical lines at the reset rule's escapes."""


def layer_style(layer: str) -> dict[str, object]:
    """:return: ``plot`` keywords of ``layer``: its colour, solid for CNN layers and dashed for the MLP"""
    return {"color": LAYER_COLORS.get(layer, "#777777"), "linestyle": "--" if layer.startswith("mlp") else "-"}


def frames_axis(ax: Axes, label: str = "frames") -> None:
    """Label the x axis in frames (environment frames, action repeat included), with 100k / 1M ticks."""
    ax.set_xlabel(label)
    ax.xaxis.set_major_formatter(EngFormatter(sep=""))
