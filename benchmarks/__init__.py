"""Benchmark scripts that write measured reports to ``benchmarks/reports/``; run each from the
repository root as ``python -m benchmarks.NAME`` (``--help`` says what it measures)."""
