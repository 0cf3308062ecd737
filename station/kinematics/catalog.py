"""Built-in models shipped as YAML next to this module; ``load_model`` also accepts a model file or a URDF."""

from __future__ import annotations

from pathlib import Path

from station.kinematics.model import Model
from station.kinematics.modelfile import ModelFileError, load_model_file, model_from_dict


def _models():
    """The folder of the built-in models (package data next to this module). Plain on disk it is read directly:
    ``importlib.resources`` costs every command that loads a model ~10 ms of imports (bench/startup.py); it is asked
    only when the package is not a folder (a zip import)."""
    here = Path(__file__).with_name("models")
    if here.is_dir():
        return here
    from importlib import resources

    return resources.files("station.kinematics") / "models"


def builtin_names() -> list[str]:
    return sorted(p.name[:-5] for p in _models().iterdir() if p.name.endswith(".yaml"))


def builtin_text(name: str) -> str:
    if name not in builtin_names():
        raise ModelFileError(f"unknown model {name!r}; built-in: {', '.join(builtin_names())}")
    return (_models() / f"{name}.yaml").read_text(encoding="utf-8")


def _builtin_doc(name: str):
    """The parsed built-in model ``name`` (values and the line of every field). libyaml parses it once; the
    parse is kept beside the file (``models/__pycache__/NAME.<python>.marshal``, as Python keeps bytecode) with
    the text it came from, and used while that text is the same: a solve or fk then imports no yaml (~20 ms of
    their start-up: bench/startup.py). A cache that cannot be written (a read-only install) or read only costs
    the parse."""
    import contextlib
    import marshal
    import os
    import sys

    from station.textfile import YamlDoc

    label, text = f"{name} (built-in)", builtin_text(name)
    folder = _models()
    cache = folder / "__pycache__" / f"{name}.{sys.implementation.cache_tag}.marshal" if isinstance(folder, Path) \
        else None
    with contextlib.suppress(Exception):  # no cache yet, another Python's, a foreign file: parse
        kept, data, lines = marshal.loads(cache.read_bytes()) if cache else (None, None, None)
        if kept == text:
            return YamlDoc(label, data, lines)
    from station.yamlfile import parse_yaml_doc

    doc = parse_yaml_doc(text, ModelFileError, label, shipped=True)
    if cache is not None:
        tmp = cache.with_name(f"{cache.name}.{os.getpid()}.tmp")
        try:
            cache.parent.mkdir(exist_ok=True)
            tmp.write_bytes(marshal.dumps((text, doc.data, doc.lines)))
            os.replace(tmp, cache)  # whole or not at all for a reader in parallel
        except (OSError, ValueError):
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
    return doc


def is_urdf(path: str | Path) -> bool:
    """A URDF by its name (``.urdf``, ``.xml``), or an existing file whose first character is ``<``."""
    p = Path(path)
    if p.suffix.lower() in (".urdf", ".xml"):
        return True
    if p.suffix.lower() in (".yaml", ".yml") or not p.is_file():
        return False
    with open(p, "rb") as f:
        return f.read(64).lstrip()[:1] == b"<"


def load_model(name_or_path: str | Path, *, tip_link: str | None = None, base_link: str | None = None) -> Model:
    """A built-in model by name (``ur5e``), a model file (``station-model/1``) or a URDF by path.

    ``tip_link``/``base_link`` choose the chain of a URDF (default: the end of the only longest chain, from
    the root of its tree); they are refused for the other kinds. Errors are ``ModelFileError`` (one line)."""
    s = str(name_or_path)
    if s.endswith(".xacro"):
        raise ModelFileError(f"{s}: a xacro file: expand it first (xacro {s} > robot.urdf) and pass the URDF")
    if Path(s).exists() and is_urdf(s) or s.lower().endswith((".urdf", ".xml")):
        from station.kinematics.urdf import load_urdf

        return load_urdf(s, tip_link=tip_link, base_link=base_link)
    if tip_link is not None or base_link is not None:
        which = "tip" if tip_link is not None else "base"
        raise ModelFileError(f"{s}: a {which} link applies to a URDF model only (this is "
                             f"{'a built-in model' if s in builtin_names() else 'not a URDF'})")
    if s in builtin_names():
        doc = _builtin_doc(s)
        return model_from_dict(doc, doc.name, shipped=True)
    if Path(s).exists() or s.endswith((".yaml", ".yml")):
        return load_model_file(s)
    raise ModelFileError(f"unknown model {s!r}: not a built-in ({', '.join(builtin_names())}) nor a file")
