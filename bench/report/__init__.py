"""Output files: the run report (telemetry, plots, video), the campaign report and atomic file writing."""
