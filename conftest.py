"""pytest's rootdir conftest: it puts the repository root on ``sys.path``, so that tests import the modules that only
tests and benchmarks use (the reference-update oracle, the random-observation env) as ``tests.<module>``."""
