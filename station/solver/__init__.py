"""Calibration solver: observations in, ``CalibrationResult`` out. Pure (numpy/scipy), SI, no I/O.

``solve`` (iterated Levenberg-Marquardt with identifiability and covariance) and the closed-form TCP
methods ``tcp_from_flange_poses``, ``tcp_scara_4point``, ``tcp_circle_fit``. See docs/solver.md."""

from station.solver.estimator import select_names, solve
from station.solver.observations import Observations, SolverInputError, observations_from_samples
from station.solver.result import CalibrationResult, ParameterEstimate
from station.solver.tcp import CircleFit, TcpFit, tcp_circle_fit, tcp_from_flange_poses, tcp_scara_4point

__all__ = [
    "CalibrationResult", "CircleFit", "Observations", "ParameterEstimate", "SolverInputError", "TcpFit",
    "observations_from_samples", "select_names", "solve", "tcp_circle_fit", "tcp_from_flange_poses", "tcp_scara_4point",
]
