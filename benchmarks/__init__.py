"""Benchmark, diagnosis and worker scripts (run as files: python benchmarks/bench/bench_core.py); _results is
their one helper."""
