"""The experiment layer: evaluation over seeds, report and plots, command lines, benchmark and
calibration. It uses :mod:`controllers` and :mod:`lfm_env`; neither of them imports it."""
