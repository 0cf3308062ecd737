"""Built-in models shipped as YAML next to this module; ``load_model`` also accepts a file path."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from station.kinematics.model import Model
from station.kinematics.modelfile import ModelFileError, load_model_file, model_from_dict


def builtin_names() -> list[str]:
    folder = resources.files("station.kinematics") / "models"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def builtin_text(name: str) -> str:
    if name not in builtin_names():
        raise ModelFileError(f"unknown model {name!r}; built-in: {', '.join(builtin_names())}")
    return (resources.files("station.kinematics") / "models" / f"{name}.yaml").read_text()


def load_model(name_or_path: str | Path) -> Model:
    """A built-in model by name (``ur5e``) or a model file by path."""
    s = str(name_or_path)
    if s in builtin_names():
        import yaml

        return model_from_dict(yaml.safe_load(builtin_text(s)), f"{s} (built-in)")
    if Path(s).exists() or s.endswith((".yaml", ".yml")):
        return load_model_file(s)
    raise ModelFileError(f"unknown model {s!r}: not a built-in ({', '.join(builtin_names())}) nor a file")
