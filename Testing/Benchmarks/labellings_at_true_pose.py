"""Does the right labelling lose the levels contest to its optimiser? (issue 11, item 3; stop 39's diagnosis)

Not a test. For an appearance-benchmark case folder already written by ``bench_appearance`` (``truth.json`` and the
X-ray file; ``--work``'s ``caseNNN/<variant>``), the pipeline is run to the levels stage with the case's clicks
unnamed (database cached in ``--cache-dir``), then every labelling the contest registered is scored three more
ways with the contest's own coarse refinement (``RegistrationParameters.refine_coarse``: GC with the landmark
term, 4 mm mu)::

    at the true pose:     f(pose_true)                      (one evaluation, no search)
    from the true pose:   min f, its search started at pose_true
    restarted:            min f, its search restarted from its own refined pose (``labelling_fit.restart``)

with f = (1 - GC) + landmark term + rotation prior (``labelling_fit``). When the true labelling's f at the true pose
beats the winner's found f, the right labelling lost to its optimiser, not to the image. The benchmark's pose is
CarmReg's pose on the same nominal geometry (checked: the script prints the largest pixel difference between the
truth's projection matrix and CarmReg's at that pose)::

    .venv/bin/python Testing/Benchmarks/labellings_at_true_pose.py /tmp/w/case191/ii-dark-log-png --cache-dir /tmp/c
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_appearance as bench  # noqa: E402

from carmreg.logic.geometry.camera import POSE_NAMES, project  # noqa: E402
from carmreg.logic.registration.image_refine import intensity_refine  # noqa: E402
from carmreg.logic.registration.labelling_fit import restart, state_context  # noqa: E402


def contest_state(folder: Path, cache_dir: str):
    """(logic, the state after the levels stage, truth) of a benchmark case folder (``caseNNN/<variant>``,
    written again there), its clicks unnamed."""
    case = int(folder.parent.name.removeprefix("case"))
    logic, state, truth = bench.prepared_case(bench.CaseMaker(second_ct=True), case, folder.name, folder, cache_dir)
    logic.run_through(state, "levels")
    return logic, state, truth


def report(state, truth: dict) -> list[str]:
    """One line per registered labelling (module docstring), the true one marked."""
    pose_true = np.array([truth["pose"][k] for k in POSE_NAMES], float)
    points = np.array([state.ct_landmarks.as_dict()[name] for name in truth["clicked"]])
    gap_px = np.abs(project(np.array(truth["projection_matrix"]), points)
                    - project(state.geometry.projection_matrix(pose_true), points)).max()
    ident, coarse = state.identification, state.parameters.refine_coarse
    level = state.pyramid.level(coarse.mu_spacing_mm)
    ctx = state_context(state, state.xray_line_integral, state.spatial.ty_mm, state.spatial.tz_mm, None)
    lines = [f"status {ident.status}, winner {'-'.join(ident.winner.labels)}, margin {ident.margin:.3f}; truth "
             f"{'-'.join(truth['clicked'])}; truth's P against CarmReg's P at the true pose: {gap_px:.2f} px"]

    def refined_from(fit, start, evaluations):
        params = dataclasses.replace(coarse, max_evaluations=evaluations)
        r = intensity_refine(level, state.geometry, start, state.xray_line_integral, state.mask, fit.points_lps_mm,
                             fit.uv_px, params)
        return f"{r.objective_end:.3f} (GC {r.similarity_end:.3f}, {r.mpde_mm:.2f} mm)"

    for fit in sorted((f for f in ident.fits if f.refined), key=lambda f: f.score):
        again = restart(ctx, fit.copy())
        mark = " <- truth" if list(fit.labels) == list(truth["clicked"]) else ""
        lines.append(f"{'-'.join(fit.labels)}{mark}: found {fit.score:.3f} (GC {fit.similarity:.3f}, "
                     f"{fit.mpde_mm:.2f} mm) at {np.round(fit.pose, 1).tolist()}; at the true pose "
                     f"{refined_from(fit, pose_true, 1)}; from the true pose {refined_from(fit, pose_true, 800)}; "
                     f"restarted {again.score:.3f} (GC {again.similarity:.3f}, {again.mpde_mm:.2f} mm)")
    lines.append(f"true pose {np.round(pose_true, 1).tolist()}")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path, help="caseNNN/<variant> folders of bench_appearance --work")
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    args = parser.parse_args(argv)
    for folder in args.folders:
        _, state, truth = contest_state(folder, args.cache_dir)
        print(f"{folder}:", *report(state, truth), sep="\n  ", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
