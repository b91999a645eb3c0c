"""Learn the latent force's hyperparameters from calibration episodes (lfm-calibrate)."""

from experiments.cli import calibrate_main

if __name__ == "__main__":
    raise SystemExit(calibrate_main())
