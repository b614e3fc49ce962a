"""Figures drawn in a forked child (``report.aside``): the value comes back, a failed or silent child is replaced
by drawing here, and ``save_result`` writes the same files either way."""

import os
import re
import time

import numpy as np
import pytest

from carmreg.logic.report import aside

pytestmark = pytest.mark.skipif(not aside.available(), reason="forking is only used on Linux")
pypdf = pytest.importorskip("pypdf")


def _sum_in_child(values: np.ndarray) -> tuple[int, float]:
    return os.getpid(), float(values.sum())


def _fails(_):
    raise ValueError("drawing failed")


def _hangs(_):
    time.sleep(30)


def test_the_child_computes_from_the_parents_memory_and_sends_the_value_back():
    values = np.arange(1000.0)
    pid, total = aside.finish(aside.start(_sum_in_child, values))
    assert pid != os.getpid() and total == 499500.0


def test_a_child_that_fails_or_stays_silent_gives_none_and_is_gone():
    assert aside.finish(aside.start(_fails, 1)) is None
    child = aside.start(_hangs, 1)
    t0 = time.perf_counter()
    assert aside.finish(child, timeout_s=0.5) is None
    assert time.perf_counter() - t0 < 5.0 and not child.process.is_alive()
    child = aside.start(_hangs, 1)  # the parent stopped before collecting it (an error, Ctrl-C)
    aside.cancel(child)
    assert not child.process.is_alive()


def _big_after(seconds: float) -> bytes:
    time.sleep(seconds)
    return bytes(4_000_000)  # far more than a pipe holds: the send blocks until read


def test_the_child_ignores_ctrl_c_and_exits_when_the_parent_is_gone():
    import signal

    child = aside.start(_big_after, 0.5)
    time.sleep(0.2)
    os.kill(child.process.pid, signal.SIGINT)  # Ctrl-C reaches the whole process group; the parent handles it
    assert len(aside.finish(child)) == 4_000_000
    child = aside.start(_big_after, 0.3)
    child.receive.close()  # as when the parent dies: nobody reads; the child must not wait forever
    child.process.join(10.0)
    assert not child.process.is_alive()


def _page_text(path) -> str:
    text = pypdf.PdfReader(str(path)).pages[0].extract_text()
    # the time it was made: the two drawings may straddle a minute
    return re.sub(r"\d{4}-\d{2}-\d{2} \d{2}:\d{2} UTC", "", text)


def _files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


@pytest.mark.parametrize("child_fails", [False, True])
def test_save_result_drawing_aside_writes_the_same_files_as_drawing_here(tmp_path, monkeypatch, child_fails):
    from test_report_page import _result

    from carmreg.logic.report import result_files

    result = _result("confident")
    clicked = {lv["label"]: lv["clicked_uv_px"] for lv in result.levels if lv["fitted"]}
    here = result_files.save_result(result, tmp_path / "here", result.xray_line_integral, clicked)
    if child_fails:  # the child's drawing raises; the parent's does not: the parent draws the child's figures
        parent, draw = os.getpid(), result_files.figures

        def figures(*args):
            if os.getpid() != parent:
                raise RuntimeError("the child's drawing failed")
            return draw(*args)
        monkeypatch.setattr(result_files, "figures", figures)
    aside_paths = result_files.save_result(result, tmp_path / "aside", result.xray_line_integral, clicked,
                                           draw_aside=True)
    assert _files(tmp_path / "here") == _files(tmp_path / "aside")
    assert set(here) == set(aside_paths)
    for key in ("convergence", "overlay", "result"):
        assert here[key].read_bytes() == aside_paths[key].read_bytes(), key
    assert _page_text(here["report"]) == _page_text(aside_paths["report"])
