"""A termination signal stops the command even when it lands inside a finaliser (where Python swallows it)."""

import signal
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import signal, sys, time
    from carmreg import signals

    # Ctrl-C as in a terminal: a job started in the background (CI, nohup) inherits SIGINT ignored
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signals.install()

    class Finalised:
        def __del__(self):
            signal.raise_signal(signal.{name})
            sum(range(100000))  # the handler runs here, inside the finaliser

    try:
        Finalised()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            sum(range(1000))
        print("ran on")
    finally:
        print("unwound")
""")


def run(name: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SCRIPT.format(name=name)], capture_output=True, text=True,
                          timeout=60)


def test_sigterm_inside_a_finaliser_still_stops_the_command_quietly():
    proc = run("SIGTERM")
    assert proc.returncode == 128 + signal.SIGTERM
    assert proc.stdout.split() == ["unwound"]
    assert proc.stderr == ""


def test_ctrl_c_inside_a_finaliser_still_interrupts():
    proc = run("SIGINT")
    assert proc.returncode != 0
    assert "ran on" not in proc.stdout and "unwound" in proc.stdout
    assert "Exception ignored" not in proc.stderr
