"""Calibration solver: observations in, ``CalibrationResult`` out. Pure (numpy only at import), SI, no I/O.

``solve`` (maximum a-posteriori Levenberg-Marquardt with priors, identifiability, posterior covariance,
outliers and the refusal of untrustworthy results), ``predict`` (the plan-time check: posterior std of
every parameter from planned poses, before anything moves) and the closed-form TCP methods
``tcp_from_flange_poses``, ``tcp_scara_4point``, ``tcp_circle_fit``. See docs/solver.md."""

from station.solver.estimator import select_names, solve
from station.solver.observations import Observations, SolverInputError, observations_from_samples
from station.solver.predict import ParameterPrediction, Prediction, predict
from station.solver.result import CalibrationResult, ParameterEstimate
from station.solver.tcp import CircleFit, TcpFit, tcp_circle_fit, tcp_from_flange_poses, tcp_scara_4point

__all__ = [
    "CalibrationResult", "CircleFit", "Observations", "ParameterEstimate", "SolverInputError", "TcpFit",
    "ParameterPrediction", "Prediction", "observations_from_samples", "predict", "select_names", "solve",
    "tcp_circle_fit", "tcp_from_flange_poses", "tcp_scara_4point",
]
