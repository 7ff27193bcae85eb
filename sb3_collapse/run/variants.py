"""
The names of the variants, one grammar for the sweep that runs them, the run that records them and the report that
reads them back (docs/sweeps.md):

- a plain variant, ``<algorithm>[-leaky][+<intervention> | +redo_periodic]``: ``drqv2``, ``td3+reset``,
  ``drqv2-leaky+redo_periodic``; the intervention done by the paper's reset rule, or ReDo every
  :data:`~sb3_collapse.monitoring.interventions.REDO_EVERY_UPDATES` updates without the rule;
- a transplant-grid cell, ``cnn-<src>_mlp-<src>`` with ``<src>`` in :data:`TRANSPLANT_SOURCES`: ``cnn-good_mlp-bad``.
"""

from __future__ import annotations

from typing import Any

from sb3_collapse.baselines import BASELINES
from sb3_collapse.errors import InputError
from sb3_collapse.monitoring.interventions import INTERVENTIONS, REDO_EVERY_UPDATES

ALGORITHMS = ("drqv2", *BASELINES)  # what ``algorithm`` trains: DrQ-v2, or SB3's TD3 or SAC (baselines.py)
LEAKY = "-leaky"  # suffix of the DrQ-v2 variants with Leaky-ReLU activations (drqv2-leaky)
PERIODIC_REDO = "redo_periodic"  # <algorithm>+redo_periodic: ReDo every REDO_EVERY_UPDATES updates, no rule
RULE_INTERVENTION = "reset"  # the intervention of the rule when none is named: <algorithm>+reset
BASE_VARIANTS = ("drqv2", f"drqv2{LEAKY}", *(algorithm for algorithm in ALGORITHMS if algorithm != "drqv2"))
PLAIN_VARIANTS = tuple(
    f"{base}{suffix}"
    for base in BASE_VARIANTS
    for suffix in ("", *(f"+{i}" for i in INTERVENTIONS), f"+{PERIODIC_REDO}")
)
BLANK_SOURCE = "blank"  # a transplant source: the fresh initialization, no donor
TRANSPLANT_SOURCES = (BLANK_SOURCE, "good", "bad")
"""Where a transplanted CNN or MLP comes from (Figure 3(a)'s rows and columns)."""
GRID_VARIANTS = tuple(f"cnn-{cnn}_mlp-{mlp}" for cnn in TRANSPLANT_SOURCES for mlp in TRANSPLANT_SOURCES)
BASELINE_VARIANT, RULE_VARIANT = "drqv2", f"drqv2+{RULE_INTERVENTION}"
"""The variants of the paper's Figure 5: DrQ-v2, and DrQ-v2 plus the rule (a sweep's default, the report's first)."""
VARIANT_FORMS = (
    f"<algorithm>, <algorithm>+<intervention> with <algorithm> in {', '.join(BASE_VARIANTS)} and <intervention> in "
    f"{', '.join(INTERVENTIONS)} (the paper's rule doing it) or {PERIODIC_REDO} (ReDo every {REDO_EVERY_UPDATES} "
    "updates, no rule), e.g. drqv2+reset, td3+redo, drqv2-leaky+redo_periodic; or a transplant-grid cell "
    f"cnn-<src>_mlp-<src> with <src> in {', '.join(TRANSPLANT_SOURCES)} (e.g. cnn-good_mlp-bad)"
)
"""The variant names, for the message that refuses an unknown one."""


def variant_name(
    algorithm: str, activation: str = "relu", reset_rule: bool = False, intervention: str | None = None,
    redo_every_updates: int = 0,
) -> str:  # fmt: skip
    """
    :return: the name of the plain variant that these ``TrainConfig`` settings run (the inverse of
        :func:`variant_settings`): ``"drqv2-leaky+redo"``
    """
    base = algorithm + (LEAKY if activation == "leaky_relu" else "")
    if reset_rule:
        return f"{base}+{intervention or RULE_INTERVENTION}"
    return f"{base}+{PERIODIC_REDO}" if redo_every_updates > 0 else base


def split_variant(variant: str) -> tuple[str, str | None]:
    """:return: ``(base, suffix)`` of a plain variant's name, ``suffix`` its intervention or ``redo_periodic``
    (``None`` without one): ``("drqv2-leaky", "redo")``; any other name is taken as a base"""
    base, plus, suffix = variant.partition("+")
    return base, (suffix if plus else None)


def transplant_sources(variant: str) -> tuple[str, str] | None:
    """:return: ``(cnn source, mlp source)`` of a transplant-grid cell ``cnn-<src>_mlp-<src>``, else ``None``"""
    if variant not in GRID_VARIANTS:
        return None
    cnn, mlp = variant.split("_")
    return cnn.removeprefix("cnn-"), mlp.removeprefix("mlp-")


def transplant_of(variant: str) -> dict[str, str] | None:
    """
    :param variant: a variant name
    :return: ``{"cnn": src, "mlp": src}`` for a transplant-grid cell, ``None`` for a plain variant
    :raises InputError: for an unknown variant, listing the valid ones
    """
    if variant in PLAIN_VARIANTS:
        return None
    sources = transplant_sources(variant)
    if sources is None:
        raise InputError(f"Unknown variant {variant!r}: use {VARIANT_FORMS}.")
    return dict(zip(("cnn", "mlp"), sources))


def variant_settings(variant: str) -> dict[str, Any]:
    """
    :param variant: a variant name (an unknown one: ``InputError``)
    :return: the ``TrainConfig`` settings it fixes: algorithm, reset_rule, intervention, activation, redo_every_updates
    """
    settings: dict[str, Any] = {
        "algorithm": "drqv2", "reset_rule": False, "intervention": None, "activation": "relu", "redo_every_updates": 0
    }  # fmt: skip
    if transplant_of(variant) is not None:
        return settings
    base, suffix = split_variant(variant)
    settings["algorithm"] = base.removesuffix(LEAKY)
    if base.endswith(LEAKY):
        settings["activation"] = "leaky_relu"
    if suffix == PERIODIC_REDO:
        settings["redo_every_updates"] = REDO_EVERY_UPDATES
    elif suffix:
        settings.update(reset_rule=True, intervention=suffix)
    return settings
