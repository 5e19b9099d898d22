"""Benchmarks: each module prints tables and rewrites its section of BENCHMARKS.md."""
