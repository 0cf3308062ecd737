"""Calibration solver: observations in, ``CalibrationResult`` out. Pure (numpy only at import), SI, no I/O.

``solve`` (maximum a-posteriori Levenberg-Marquardt with priors, identifiability, posterior covariance,
outliers and the refusal of untrustworthy results), ``predict`` (the plan-time check: posterior std of
every parameter from planned poses, before anything moves) and the closed-form TCP methods
``tcp_from_flange_poses``, ``tcp_scara_4point``, ``tcp_circle_fit``. See docs/solver.md.

The names are imported on first use (PEP 562): ``station solve`` loads the estimator, not the plan-time
prediction or the TCP methods (start-up time, measured by bench/startup.py)."""

from station.lazy import lazy_names

_WHERE = {
    "select_names": "station.solver.estimator", "solve": "station.solver.estimator",
    "Observations": "station.solver.observations", "SolverInputError": "station.solver.observations",
    "observations_from_samples": "station.solver.observations",
    "ParameterPrediction": "station.solver.predict", "Prediction": "station.solver.predict",
    "predict": "station.solver.predict",
    "CalibrationResult": "station.solver.result", "ParameterEstimate": "station.solver.result",
    "CircleFit": "station.solver.tcp", "TcpFit": "station.solver.tcp", "tcp_circle_fit": "station.solver.tcp",
    "tcp_from_flange_poses": "station.solver.tcp", "tcp_scara_4point": "station.solver.tcp",
}
__all__ = sorted(_WHERE)
__getattr__ = lazy_names(__name__, _WHERE)
