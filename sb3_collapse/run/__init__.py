"""One training run: its settings, run folder, runner and what it writes beside the model (docs/layout.md). This
``__init__`` imports nothing: import the names from their modules."""
