"""One training run: its settings (:mod:`~sb3_collapse.run.config`, each declared once, and what is generated from
them, :mod:`~sb3_collapse.run.settings`: the flags, ``--show-settings``, the tables of ``docs/presets.md``), its run
folder (:mod:`~sb3_collapse.run.folder`), the run itself (:mod:`~sb3_collapse.run.runner`: ``train``), and the
plumbing around the algorithm, what a run writes and measures beside the model (replay data and snapshots, the
time split of ``learn()``, the CPU allocator's tuning). ``python -m sb3_collapse.train`` is its command line; the
sweep, the probe and the report import these modules, never the command's. It imports ``sb3_collapse.drqv2``; the
algorithm never imports it. Import the names from their modules: this ``__init__`` imports nothing, so that the
checkpoints and the probe import one module of the package without the runner (and without an import cycle)."""
