"""Benchmarks (``stagectl bench models|io|control|loop``). Timing and speed live here, never in tests."""
