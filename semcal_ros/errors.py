"""The package's error types: callers decide by type, never by the wording of a message.

Every message is still one line naming the problem (the CLI prints it, a node logs it or puts it
in the action result), but what a caller *does* with it — say "calibration failed" once, keep the
held map, answer a goal as cancelled — follows from the type raised where the message is made:

* :class:`InputError` — the input cannot be used (a file, a message, a parameter, a goal). A
  ``ValueError``, so code catching bad input as ``ValueError`` keeps working.
* :class:`UnknownParameter` — an :class:`InputError` naming parameters nobody declares.
* :class:`CalibrationFailed` — the inputs were fine but the search found nothing worth publishing
  (a degenerate best pose). Its message starts with "calibration failed:"; it carries the
  evaluations and seconds spent, which the action result reports.
* :class:`Cancelled` — the caller asked to stop (``should_stop``), or a queued job was dropped
  before it started.

No ROS and no engine imports here: every layer may raise these.
"""

from __future__ import annotations


class InputError(ValueError):
    """Input that cannot be used; the message names the problem in one line."""


class UnknownParameter(InputError):
    """A parameter name nobody declares (a typo in a parameter file or a goal)."""


class CalibrationFailed(ValueError):
    """The search ran but its best result must not be published.

    ``reason`` says why; ``str()`` is the one-line message, ``PREFIX`` + reason."""

    PREFIX = "calibration failed: "

    def __init__(self, reason: str, evaluations: int = 0, seconds: float = 0.0) -> None:
        super().__init__(self.PREFIX + reason)
        self.reason = reason
        self.evaluations = int(evaluations)
        self.seconds = float(seconds)


class Cancelled(Exception):
    """The work stopped because the caller asked it to (or the job was dropped before it ran)."""


__all__ = ["CalibrationFailed", "Cancelled", "InputError", "UnknownParameter"]
