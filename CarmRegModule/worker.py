"""Runs the registration logic off the GUI thread.

``RegistrationWorker(logic, job)`` is a QThread; ``job(logic, report_stage)`` does the work (prepare, stages,
result) and returns what the GUI needs. The logic's ``progress(stage, fraction, message)`` callback is called
from this thread; Qt queues the ``progress`` signal to the GUI thread. Cancel = ``logic.cancel()``; the logic
raises ``CancelledError`` at its next check (the worker also stops between stages) and the worker reports it
through ``failed``.
"""

from __future__ import annotations

import traceback

from qtpy import QtCore

from carmreg.logic.errors import CancelledError


class RegistrationWorker(QtCore.QThread):
    """One background job on a CarmRegLogic."""

    progress = QtCore.Signal(str, float, str)   # stage, fraction 0..1, message
    stage_done = QtCore.Signal(object)           # StageResult
    succeeded = QtCore.Signal(object)           # the job's return value
    failed = QtCore.Signal(object, str)         # exception, traceback text

    def __init__(self, logic, job, parent=None):
        super().__init__(parent)
        self.logic = logic
        self.job = job
        self.logic.progress = self._progress
        self._cancel_requested = False

    def _progress(self, stage: str, fraction: float, message: str) -> None:
        if self._cancel_requested:
            self.logic.cancel()  # again: preparing a run clears the logic's flag
        self.progress.emit(str(stage), float(fraction), str(message))

    def _stage_done(self, stage) -> None:
        self.stage_done.emit(stage)
        if self._cancel_requested:
            raise CancelledError("registration cancelled by the user")

    def run(self) -> None:
        try:
            value = self.job(self.logic, self._stage_done)
        except Exception as exc:  # noqa: BLE001 - handed to the GUI thread, which shows it
            self.failed.emit(exc, traceback.format_exc())
            return
        self.succeeded.emit(value)

    def cancel(self) -> None:
        self._cancel_requested = True
        self.logic.cancel()
