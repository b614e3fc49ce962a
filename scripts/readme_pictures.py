"""Regenerate the README's pictures of the window and the report page on the embedded sample case.

    xvfb-run -a .venv/bin/python scripts/readme_pictures.py [OUT_DIR]   (default: Resources/Screenshots)

main_window.png: three unnamed clicks, registered, the Check step (1600 x 1000);
contradicted.png: the clicks named one level too low (T11, T12, L1 for T10, T11, T12): the red banner, the
names drawn red with "?" and the one-step "Use the names the image supports" (1280 x 720);
report_page.png: the one-page report of the main window's result (report.page, as the PDF).
"""

from __future__ import annotations

import sys
from pathlib import Path

from carmreg.app import _focus_first_point
from carmreg.logic.report.page import write_report_png
from carmreg.logic.resources import cache_dir
from carmreg.main_window import CarmRegWidget
from carmreg.qt_common import ScriptedDialogs, ensure_app, process_events


def _window(size):
    window = CarmRegWidget(dialogs=ScriptedDialogs(), autosave=False)
    window.parameter_overrides = {"cache_dir": str(cache_dir())}
    window.resize(*size)
    window.show()
    process_events(50)
    window.load_sample_case()
    window.ct_store.select(None)
    _focus_first_point(window)
    return window


def main(out: Path) -> None:
    ensure_app()
    out.mkdir(parents=True, exist_ok=True)
    window = _window((1600, 1000))
    store = window.xray_store
    store.rename_many({p.id: None for p in store.points()}, "Forget the names")
    window.run_registration(wait=True)
    window.set_step(4)
    process_events(100)
    print(window.save_screenshot(out / "main_window.png", "window"))
    x = window.xray
    print(write_report_png(out / "report_page.png", window.result, x.pixels, window.shown_clicks(), x.bone_dark,
                           composite_rgb=window.overlay_view.composite_rgb(), dpi=110))
    window.discard_and_close()

    window = _window((1280, 720))
    store = window.xray_store
    shift = {"T10": "T11", "T11": "T12", "T12": "L1"}
    for point in sorted(store.points(), key=lambda p: -int(p.label[1:]) if p.label[0] == "T" else 0):
        store.rename(point.id, shift[point.label])
    window.run_registration(wait=True)
    window.set_step(4)
    process_events(100)
    print(window.save_screenshot(out / "contradicted.png", "window"))
    window.discard_and_close()


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "Resources" / "Screenshots")
