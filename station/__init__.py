"""Robot calibration station. The scripted API (docs/scripting.md) is re-exported here lazily, so that
``import station`` stays cheap for the command line: ``station.connect``, ``station.session``, ``station.run``,
``station.resume``, ``station.solve``, ``station.load_model``."""

_API = {"connect", "session", "run", "resume", "solve", "load_procedure", "Session", "Outcome"}


def __getattr__(name: str):
    if name in _API:
        from station import api

        return getattr(api, name)
    if name == "load_model":
        from station.kinematics import load_model

        return load_model
    raise AttributeError(f"module 'station' has no attribute {name!r}")


__all__ = sorted(_API | {"load_model"})
