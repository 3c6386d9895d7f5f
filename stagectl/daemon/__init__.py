"""The service shell: lifecycle, signals, sd_notify, control socket, telemetry."""
