"""Learn the latent force's hyperparameters from calibration episodes (lfm-calibrate)."""

from experiments.calibration import main

if __name__ == "__main__":
    raise SystemExit(main())
