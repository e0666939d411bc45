"""Benchmarks of kamino as library code: ``kamino bench`` and ``python -m kamino.bench.NAME``."""
