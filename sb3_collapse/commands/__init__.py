"""The command lines (train, sweep, probe, report, reproduce, zoo) and the folder pipelines they run: each reads
folders, calls probe/ to compute and report/ to draw, and writes folders; the flag machinery of every command in
:mod:`cli`."""
