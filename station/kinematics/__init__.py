"""Kinematic models (DH, MDH + Hayati beta, POE), batched FK, analytic Jacobians, numeric IK, catalog.

Pure: numpy/scipy only. Everything SI (m, rad). The names are imported on first use (PEP 562): loading a
model does not load the IK (start-up time, measured by bench/startup.py)."""

from station.lazy import lazy_names

_WHERE = {
    "builtin_names": "station.kinematics.catalog", "builtin_text": "station.kinematics.catalog",
    "load_model": "station.kinematics.catalog",
    "IKResult": "station.kinematics.ik", "solve_ik": "station.kinematics.ik",
    **dict.fromkeys(["Encoder", "Joint", "Model", "from_dh", "from_mdh", "from_poe", "screws_of"],
                    "station.kinematics.model"),
    **dict.fromkeys(["ModelFileError", "dump_model", "load_model_file", "model_from_dict", "model_to_dict"],
                    "station.kinematics.modelfile"),
}
__all__ = sorted(_WHERE)
__getattr__ = lazy_names(__name__, _WHERE)
