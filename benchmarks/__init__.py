"""Reproducible measurements (`python -m benchmarks.NAME`); they report, they never gate CI."""
