"""Experiment plumbing around the algorithm: what a training run writes and measures beside the model (replay and
snapshots, the time split of ``learn()``, the CPU allocator's tuning). It imports ``sb3_collapse.drqv2``;
the algorithm never imports it."""
