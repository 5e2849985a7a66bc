"""The drift watch of one camera over successive checks: its reference and the confirmation.

A single :func:`~semcal_ros.engine.drift.check_drift` judges one label image. Watching a camera
adds two rules (docs/drift.md), kept here without ROS so that ``calibration_monitor`` and
``semcal check`` apply the same ones and they can be tested without DDS:

* **The reference.** A coarse search never ends exactly at a full-resolution calibration, even
  when nothing moved. The first judged check after a calibration (or a new map) is therefore the
  reference later checks count drift from — but only if that check, judged alone, found no drift;
  otherwise checks stay absolute. The reference check itself is reported as OK with
  :data:`REFERENCE_MESSAGE`.
* **Confirmation.** A level is shown only after ``confirm`` checks in a row agree on it; "ok" and
  "unknown" (cannot judge) are shown at once. A check whose level is not shown yet says
  "(confirming k/n)".

* **The window** (``window`` > 1, a static camera): a check judges the per-pixel fusion of the
  last ``window`` label images the watch was given (:func:`~semcal_ros.engine.frames.fuse_labels`),
  so a passing bus or a flickering segmenter does not read as drift.

The watch holds no lock: a node serialises its calls (it runs the check itself, the expensive
part, outside its lock). A check started before the calibration changed is recognised by its
``epoch`` and never becomes the new calibration's reference.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from semcal_ros.engine.drift import DriftChecker, DriftReport
from semcal_ros.engine.frames import fuse_labels
from semcal_ros.engine.pose import Pose

#: The message of the check that became the reference.
REFERENCE_MESSAGE = "reference check: later checks count drift from here"


@dataclass(frozen=True)
class Verdict:
    """What one check means for the watched camera."""

    report: DriftReport  # the check (the reference check's says so in its message)
    shown: str  # the level to show after confirmation: ok / warn / error / unknown
    streak: int  # the latest checks in a row (at most ``confirm``) with this one's level
    confirm: int

    @property
    def pending(self) -> bool:
        """The check's level differs from the one shown: it still waits for confirmation."""
        return self.report.level != self.shown

    @property
    def raised(self) -> bool:
        """A confirmed WARN or ERROR: worth a log line (and, on ERROR, a recalibration)."""
        return self.shown in ("warn", "error") and not self.pending

    @property
    def message(self) -> str:
        """The one-line text a status or drift message carries."""
        r = self.report
        return (("cannot judge: " if not r.judged else "") + r.message
                + (f" (confirming {self.streak}/{self.confirm})"
                   if self.pending and r.judged else ""))


@dataclass
class DriftWatch:
    """One camera's reference, confirmation streak and shown level (see the module docstring)."""

    confirm: int = 2
    take_reference: bool = True  # False: every check is absolute (no image known to match)
    reference: DriftReport | None = None
    referenced: bool = False  # the first judged check of this calibration has been made
    shown: str = "unknown"
    streak: list[str] = field(default_factory=list)
    checks: int = 0
    last: DriftReport | None = None
    epoch: int = 0  # bumped by every reset: checks of an older calibration are told apart
    window: int = 1  # label images fused per check (a static camera); 1 = the newest alone
    recent: deque = field(default_factory=deque)  # the last ``window`` distinct label images

    def __post_init__(self) -> None:
        if self.confirm < 1:
            raise ValueError(f"confirm must be >= 1, got {self.confirm}")
        if self.window < 1:
            raise ValueError(f"label window must be >= 1 frames, got {self.window}")
        self.recent = deque(self.recent, maxlen=self.window)

    def windowed(self, labels: np.ndarray | None) -> np.ndarray | None:
        """The label image a check judges: with ``window`` > 1 ``labels`` joins the window (the
        same image object given again does not count twice; another size starts it again) and
        the window's fusion is returned; else ``labels`` itself."""
        if labels is None or self.window == 1:
            return labels
        if self.recent and self.recent[-1].shape != labels.shape:
            self.recent.clear()
        if not self.recent or self.recent[-1] is not labels:
            self.recent.append(labels)
        return fuse_labels(list(self.recent)).labels if len(self.recent) > 1 else labels

    def new_calibration(self) -> None:
        """A new calibration: no reference, and the streak starts again."""
        self.reference, self.referenced, self.streak = None, False, []
        self.epoch += 1

    def new_map(self) -> None:
        """A new map: the reference is taken again (the streak goes on)."""
        self.reference, self.referenced = None, False
        self.epoch += 1

    def check(self, checker: DriftChecker, labels: np.ndarray | None,
              calibrated: Pose | None = None) -> Verdict:
        """Run one check (from the reference, if any) of ``labels`` (with a window: of the
        window's fusion, :meth:`windowed`) and :meth:`observe` it."""
        epoch = self.epoch
        report = checker.check(self.windowed(labels), calibrated, reference=self.reference)
        return self.observe(report, epoch)

    def observe(self, report: DriftReport, epoch: int | None = None) -> Verdict:
        """Take one check's report (``epoch``: :attr:`epoch` when the check started; a report
        from before the latest reset counts for confirmation but never as the reference)."""
        current = epoch is None or epoch == self.epoch
        if report.judged and not self.referenced and current and self.take_reference:
            self.referenced = True
            if report.level == "ok":
                self.reference = report
                report = replace(report, message=REFERENCE_MESSAGE, drift_translation_m=0.0,
                                 drift_rotation_deg=0.0, drift_xyz_m=(0.0, 0.0, 0.0),
                                 raw_vector=None, raw_gain=0.0, view=None)
        self.checks += 1
        self.last = report
        self.streak = (self.streak + [report.level])[-self.confirm:]
        agreeing = _trailing(self.streak, report.level)
        if agreeing == self.confirm or report.level in ("ok", "unknown"):
            self.shown = report.level
        return Verdict(report, self.shown, agreeing, self.confirm)


def _trailing(levels: list[str], level: str) -> int:
    """How many of the latest ``levels`` in a row equal ``level``."""
    count = 0
    for earlier in reversed(levels):
        if earlier != level:
            break
        count += 1
    return count


__all__ = ["REFERENCE_MESSAGE", "DriftWatch", "Verdict"]
