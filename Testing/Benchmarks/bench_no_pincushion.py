"""The appearance benchmark with the image intensifier's pincushion switched off (stop 22's experiment).

Not a test. ``bench_appearance.py`` with every argument passed on, except that the pincushion drawn for an
intensifier scene has k = 0 and no vertical stretch. Its random draws are still made, so the pose, the per-level
motion, the K-wires, the noise and the click errors are those of the distorted run of the same case: the
difference in the levels not clicked is the distortion's alone. CarmReg's camera is a pinhole::

    .venv/bin/python Testing/Benchmarks/bench_no_pincushion.py --work /tmp/nd --out /tmp/nd \\
        --cases 10 --first 13 --half report --ct chest --variants ii-dark-log-png,ii-bright-log-png \\
        --modes unnamed,named
"""

from __future__ import annotations

import dataclasses
import sys

import appearance as app
import bench_appearance as bench

_draw_pincushion = app.draw_pincushion


def no_pincushion(rng, detector) -> app.Pincushion:
    """The pincushion the case would draw (the same random numbers consumed), with k = 0 and no stretch."""
    return dataclasses.replace(_draw_pincushion(rng, detector), k_per_mm2=0.0, stretch_y=0.0)


if __name__ == "__main__":
    app.draw_pincushion = no_pincushion
    sys.exit(bench.main(sys.argv[1:]))
