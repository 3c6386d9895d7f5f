"""Control laws (pure: no clock, no I/O, no logging). See ``api`` for the shared types."""
