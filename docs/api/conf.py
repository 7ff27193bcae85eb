"""Sphinx configuration of the API reference: ``python -m sphinx -W -b html docs/api build/api``."""

import inspect
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # a clone's package, installed or not
import sb3_collapse

project = "sb3-collapse"
release = version = sb3_collapse.__version__
extensions = ["sphinx.ext.autodoc"]
autodoc_default_options = {"members": True, "undoc-members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
html_theme = "alabaster"
FIELD = re.compile(r"^:(?:param|type|returns?|rtype|raises?|var|ivar|cvar|yields?)\b")


def indent_field_continuations(app, what, name, obj, options, lines: list[str]) -> None:
    """The package's one-line-opening docstrings (``:return: ...`` continued on the next line at the same indent):
    indent a field's continuation lines, as reST wants them. A constant without a docstring gets none."""
    if what == "data" and "\n".join(lines).strip() == inspect.cleandoc(type(obj).__doc__ or ""):
        lines.clear()  # a constant without a docstring of its own: not its type's
    in_field = False
    for i, line in enumerate(lines):
        if FIELD.match(line):
            in_field = True
        elif not line.strip():
            in_field = False
        elif in_field and not line.startswith(" "):
            lines[i] = "   " + line


def setup(app) -> None:
    app.connect("autodoc-process-docstring", indent_field_continuations)
