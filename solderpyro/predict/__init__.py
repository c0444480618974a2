"""Predictions in the solder from a calibration's posterior: stresses, inelastic strains and
the inelastic strain energy density per cycle, with credible bands, on the calibration's
specimen or the user's assembly and cycle (``solderpyro predict``; docs/predict.md).

>>> from solderpyro.predict import predict
>>> pred = predict("runs/demo/calibration", n_draws=200)      # doctest: +SKIP
>>> pred.bands[("dW", "upper_interface", 1)].median             # doctest: +SKIP
"""

from solderpyro.predict.run import N_DRAWS, HistoryPoint, Prediction, default_points, predict

__all__ = ["N_DRAWS", "HistoryPoint", "Prediction", "default_points", "predict"]
