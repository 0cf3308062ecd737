"""The options that choose a model, shared by every command that takes ``--model`` (solve, fk, model ...).

Each is declared once (:class:`station.cli.optspec.Opt`, in ``MODEL_OPTIONS``). The click commands (solve, fk)
take ``MODEL_OPTIONS`` as click options; typer commands use ``MODEL``, ``TIP_LINK``, ``BASE_LINK``, ``PAYLOAD``
as parameter defaults (built on first access, so that the click commands never import typer) and load through
:func:`load_cli_model`::

    def cmd(model: str = MODEL, tip_link: str = TIP_LINK, base_link: str = BASE_LINK, payload: str = PAYLOAD):
        m = load_cli_model(model, tip_link, base_link, payload)
"""

from __future__ import annotations

from station.cli.optspec import REQUIRED, Opt
from station.quantity import parse_payload  # noqa: F401  (the --payload reading: commands import it from here)

MODEL_OPTIONS = [
    Opt("model", "--model", "Built-in model name, model file (station-model/1) or URDF", REQUIRED),
    Opt("tip_link", "--tip-link", "URDF: the link at the end of the chain (default: the end of the only longest "
                                  "chain)"),
    Opt("base_link", "--base-link", "URDF: the link the chain starts from (default: the root)"),
    Opt("payload", "--payload", "Mass at the tool, e.g. 0.1kg or 250g, optionally with its centre in the tool "
                                "frame: 0.5kg@0,0,30mm (loads the joints: compliance)"),
]
_TYPER_NAMES = {"MODEL": "model", "TIP_LINK": "tip_link", "BASE_LINK": "base_link", "PAYLOAD": "payload"}


def __getattr__(name: str):
    """``MODEL``/``TIP_LINK``/``BASE_LINK``/``PAYLOAD``: the typer options, made on first use (PEP 562)."""
    if name in _TYPER_NAMES:
        opt = next(o for o in MODEL_OPTIONS if o.name == _TYPER_NAMES[name]).typer()
        globals()[name] = opt
        return opt
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def load_cli_model(model: str, tip_link: str | None = None, base_link: str | None = None,
                   payload: str | None = None):
    """The model named on the command line; bad input raises errors that ``station`` prints as one line."""
    from station.kinematics import load_model

    m = load_model(model, tip_link=tip_link, base_link=base_link)  # ModelFileError: one line, exit 2
    warn_lines((getattr(m, "source", None) or {}).get("warnings") or [])
    if payload:
        mass, com = parse_payload(payload)
        m = m.with_payload(mass, com)
    return m


def warn_lines(lines) -> None:
    """What the station accepted but the user should know (a URDF limit it ignores, readings beyond a joint's
    limits): one ``station: warning: ...`` line each on stderr; stdout stays the command's data."""
    import sys

    for line in lines:
        print(f"station: warning: {line}", file=sys.stderr, flush=True)
