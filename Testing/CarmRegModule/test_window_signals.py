"""A termination signal (Ctrl-C in the terminal, kill, logout) closes the window at once, keeping unsaved work."""

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest
from qtpy import QtCore

from carmreg.logic.io.session import load_session


class _Window:
    """Records the call ``qt_signals`` makes, and ends the test's event loop."""

    def __init__(self, loop):
        self.loop, self.received = loop, []

    def close_for_signal(self, signum):
        self.received.append(signum)
        self.loop.exit(0)


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP", "SIGINT"])
def test_a_signal_reaches_the_window_while_the_event_loop_waits(qapp, name):
    """The signal lands while Qt waits for events (no Python running, where a bare Python handler never fires):
    the wakeup socket brings the handler in and the window is asked to close, with the signal's number."""
    from carmreg.qt_signals import quit_window_on_signals, restore_default_signals

    signum = int(getattr(signal, name))
    loop = QtCore.QEventLoop()
    window = _Window(loop)
    quit_window_on_signals(qapp, window)
    try:
        # sent from another thread while the main thread waits inside Qt (a Qt timer would run Python itself)
        threading.Timer(0.2, os.kill, (os.getpid(), signum)).start()
        QtCore.QTimer.singleShot(10_000, lambda: loop.exit(-1))  # the test's own time limit
        assert loop.exec() == 0
    finally:
        restore_default_signals(qapp)
    assert window.received == [signum]


@pytest.mark.parametrize("dirty", [True, False])
def test_closing_for_a_signal_keeps_unsaved_work_in_the_autosave(window, tmp_path, monkeypatch, dirty):
    ended = []
    monkeypatch.setattr(window, "_end_application", ended.append)
    window.ct_store.add("T12", [1.0, 2.0, 3.0])
    window.autosave_now()
    window._dirty = dirty  # False: as after saving the session
    window.close_for_signal(signal.SIGTERM)
    assert ended == [143] and window.quit_code == 143
    autosave = tmp_path / "state" / f"autosave-{os.getpid()}.carmreg.json"
    if dirty:
        assert [p["label"] for p in load_session(autosave).ct_points] == ["T12"]
    else:
        assert not autosave.exists()


SCRIPT = textwrap.dedent("""
    import sys
    from qtpy import QtCore
    from carmreg.qt_common import ensure_app
    app = ensure_app(offscreen=False)
    QtCore.QTimer.singleShot(0, lambda: print("ready", flush=True))  # the window is up, its handlers in
    from carmreg.app import run_gui
    sys.exit(run_gui())
""")


@pytest.mark.skipif(not os.environ.get("DISPLAY"), reason="needs a display (the suite runs under xvfb-run)")
def test_the_application_ends_on_sigterm_with_exit_code_143(qapp, tmp_path):
    env = {**os.environ, "HOME": str(tmp_path), "XDG_STATE_HOME": str(tmp_path / "state")}
    env.pop("QT_QPA_PLATFORM", None)
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, env=env)
    watchdog = threading.Timer(90, proc.kill)  # a window that never comes up fails the test, not the suite
    watchdog.start()
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.5)  # idle in the event loop
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 128 + signal.SIGTERM
    finally:
        watchdog.cancel()
        proc.kill()
        proc.wait()
