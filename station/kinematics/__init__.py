"""Kinematic models (DH, MDH + Hayati beta, POE), batched FK, analytic Jacobians, numeric IK, catalog.

Pure: numpy/scipy only. Everything SI (m, rad)."""

from station.kinematics.catalog import builtin_names, builtin_text, load_model
from station.kinematics.ik import IKResult, solve_ik
from station.kinematics.model import Encoder, Joint, Model, from_dh, from_mdh, from_poe, screws_of
from station.kinematics.modelfile import ModelFileError, dump_model, load_model_file, model_from_dict, model_to_dict

__all__ = [
    "Encoder", "IKResult", "Joint", "Model", "ModelFileError", "builtin_names", "builtin_text", "dump_model",
    "from_dh", "from_mdh", "from_poe", "load_model", "load_model_file", "model_from_dict", "model_to_dict",
    "screws_of", "solve_ik",
]
