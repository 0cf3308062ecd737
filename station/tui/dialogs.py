"""The jog UI's dialogs: a yes/no question (discard, export, go near, quit), the write-back table and the key
help. Enter never confirms (it is the record key); STOP (space, x, ctrl+c) reaches the app over every one."""

from __future__ import annotations

import numpy as np
from rich.text import Text
from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import Button, Static

from station.tui.approach import NearPlan
from station.tui.controller import ExportPlan, WritebackPlan


class ConfirmScreen(ModalScreen[bool]):
    """A yes/no question; enter does not confirm (it is the record key)."""

    BINDINGS = [Binding("y", "confirm", "yes"), Binding("n,escape", "cancel", "no")]
    AUTO_FOCUS = "#cf-no"
    DEFAULT_CSS = """
    ConfirmScreen { align: center middle; }
    #cf-box { width: 76; max-width: 100%; height: auto; max-height: 100%; border: thick $warning;
              background: $surface; padding: 0 1; }
    #cf-buttons { height: auto; margin-top: 1; }
    #cf-buttons Button { margin-right: 2; }
    """

    def __init__(self, question: str, yes: str = "Yes (y)") -> None:
        super().__init__()
        self.question, self.yes = question, yes

    def compose(self) -> ComposeResult:
        with Vertical(id="cf-box"):
            yield Static(Text(self.question, style="bold"), id="cf-question")
            with Horizontal(id="cf-buttons"):
                yield Button(self.yes, variant="error", id="cf-yes")
                yield Button("No (n)", variant="primary", id="cf-no")

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "cf-yes")

    def action_confirm(self) -> None:
        self.dismiss(True)

    def action_cancel(self) -> None:
        self.dismiss(False)


class QuitScreen(ConfirmScreen):
    """Quit with something at stake (motion, compliance, a session with samples); ctrl+q again also quits."""


class NearScreen(ConfirmScreen):
    """Confirm a planned "go near" before anything moves."""

    def __init__(self, plan: NearPlan, question: str) -> None:
        super().__init__(question, yes="Go (y)")
        self.plan = plan


def export_question(plan: ExportPlan) -> str:
    return (f"Export the calibration for the controller?\n\nThe controller keeps its own calibration: nothing is "
            f"written to the robot, it stays unchanged. Files (calibration.conf, URDF, YAML) go to\n  {plan.folder}\n"
            "for the integrator to install.")


def near_question(plan: NearPlan, kind: str) -> str:
    how = ", turning to point into it" if plan.reoriented else ", keeping its orientation"
    slow = " (raise the speed with + first)" if plan.seconds > 20 else ""
    lines = [f"Go near {plan.label} ({kind})?", "",
             f"The tool moves to {plan.standoff * 1e3:g} mm out from {plan.label} along its approach{how}: "
             f"{plan.travel * 1e3:.0f} mm of travel at up to {plan.cap * 1e3:g} mm/s, about "
             f"{plan.seconds:.0f} s{slow}."]
    lines += [f"The path {note}." for note in plan.notes]
    lines += ["", "Planned in the nominal model and checked against the keep-out; the point is only as exact as the "
              "cell file. STOP: space or ctrl+c. Then jog in with small steps, watching the distance."]
    return "\n".join(lines)


def quit_question(concerns: list[str]) -> str:
    return "Quit station jog?\n\n" + "\n".join(f"• {c}" for c in concerns) + "\n\ny or ctrl+q quits, n stays."


class WritebackScreen(ModalScreen[bool]):
    """Explicit confirmation with the before/after of every value the write would change."""

    BINDINGS = [Binding("y", "confirm", "write to robot"), Binding("n,escape", "cancel", "cancel")]
    AUTO_FOCUS = "#wb-no"  # enter (the record key) must never confirm a write by accident
    DEFAULT_CSS = """
    WritebackScreen { align: center middle; }
    #wb-box { width: 90; max-width: 100%; height: auto; max-height: 100%; border: thick $warning;
              background: $surface; padding: 0 1; }
    #wb-buttons { height: auto; margin-top: 1; }
    #wb-buttons Button { margin-right: 2; }
    """

    def __init__(self, plan: WritebackPlan) -> None:
        super().__init__()
        self.plan = plan

    def compose(self) -> ComposeResult:
        t = Text()
        if self.plan.kind == "restore":
            t.append("Restore the calibration the robot had before this session's write-back?\n\n", style="bold")
        else:
            t.append("Write joint zero offsets to the robot?\n\n", style="bold")
        t.append(f"{'parameter':<12}{'before [deg]':>16}{'correction':>14}{'after [deg]':>16}\n", style="bold")
        for name in sorted(self.plan.after, key=lambda n: (len(n), n)):
            b = self.plan.before.get(name, 0.0)
            a = self.plan.after[name]
            c = self.plan.corrections.get(name)
            mark = "" if c is None else f"{np.rad2deg(c):+14.4f}"
            t.append(f"{name:<12}{np.rad2deg(b):+16.4f}{mark:>14}{np.rad2deg(a):+16.4f}\n",
                     style="bold yellow" if c is not None or a != b else "")
        if self.plan.kind == "restore":
            t.append("\nThe values come from this session's pre-image (calibration-backup.json).\n")
        else:
            t.append("\nThe pre-image is journaled and saved as calibration-backup.json before writing.\n")
        with Vertical(id="wb-box"):
            yield Static(t, id="wb-table")
            with Horizontal(id="wb-buttons"):
                yield Button("Write (y)", variant="error", id="wb-yes")
                yield Button("Cancel (n)", variant="primary", id="wb-no")

    def on_button_pressed(self, event: Button.Pressed) -> None:
        self.dismiss(event.button.id == "wb-yes")

    def action_confirm(self) -> None:
        self.dismiss(True)

    def action_cancel(self) -> None:
        self.dismiss(False)


class HelpScreen(ModalScreen[None]):
    """Every key, for a terminal too small to show the keys panel."""

    BINDINGS = [Binding("escape,question_mark,enter", "close", "close")]
    DEFAULT_CSS = """
    HelpScreen { align: center middle; }
    #help-box { width: 66; max-width: 100%; height: auto; max-height: 100%; border: thick $primary;
                background: $surface; padding: 0 1; }
    """

    def __init__(self, text: Text) -> None:
        super().__init__()
        self.text = text

    def compose(self) -> ComposeResult:
        with Vertical(id="help-box"):
            yield Static(self.text)
            yield Static(Text("escape or ? closes", style="dim"))

    def action_close(self) -> None:
        self.dismiss(None)
