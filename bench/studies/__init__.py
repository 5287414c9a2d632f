"""Controller design studies beyond sweeps: the Gymnasium environment (:mod:`bench.studies.lander_env`)."""
