"""Offline analysis: recordings I/O, friction identification and the discovery workflow."""
