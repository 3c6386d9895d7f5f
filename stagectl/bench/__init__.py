"""Benchmarks (``stagectl bench models|io|control|loop|telemetry``). Timing and speed live here, never in tests."""
