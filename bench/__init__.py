"""The benchmarks: one module a bench, run from the repository root as
``python -m bench.NAME [options]`` (``--help`` lists a bench's options); the shared
arguments, protocols, timing and JSON record are :mod:`bench.harness`'s."""
