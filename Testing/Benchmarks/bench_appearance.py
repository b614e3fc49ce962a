"""Benchmark: level names and pose on X-rays whose appearance CarmReg was not tuned on (issue 11, item 4).

Not a test: run it by hand (long; resumable: cases already in the JSON are skipped)::

    .venv/bin/python Testing/Benchmarks/bench_appearance.py --cases 24 --modes unnamed,named,wrong \\
        --out Testing/Benchmarks

Cases alternate between the sample chest CT (T1-L1) and the second CT (``second_ct.py``, L1-S1, 3 mm voxels;
skipped when ../shared is absent): every third case (index % 3 == 2) uses the second CT. Each case: a pose and
per-level motion drawn as bench_levels draws them, rendered on an image intensifier and on a flat panel, then
every variant of ``appearance.VARIANTS`` (an appearance chain written independently of CarmReg's simulator:
see ``appearance.py``) is stored as a real file (16-bit PNG, TIFF, 8-bit JPEG, DICOM with and without
PixelIntensityRelationshipSign, MONOCHROME1) and registered by ``carmreg register`` **as a subprocess** (the
whole process, the DRR database cached in ``--cache-dir``), in the modes:

- ``unnamed``: the three clicks without names; ``named``: the right names; ``wrong``: every name one level off
  (up or down at random); ``none``: no clicks.

Halves: even case index = "tune" (for choosing thresholds), odd = "report" (the figures quoted). The answer's
labels are right when: unnamed, the assigned labels are the true ones; named / wrong, the names given are
(always / never); none, every visible level is named correctly by the found pose. Pose-PDE: every visible level
not clicked, CT centroid projected with the found and the true P (mirrored display: the true P flipped), mm on the
detector. Image-PDE: the same levels' CT centroids projected with the found P against where each vertebra shows in
the X-ray (after its per-level motion and the intensifier's pincushion), and the true P's the same way. Polarity:
``result.json["appearance"]["polarity"]`` when present, else what the reader assumed (``load_xray(...).bone_dark``,
marked "assumed").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import appearance as app  # noqa: E402
from bench_registration import load_case  # noqa: E402
from second_ct import CENTROIDS_PATH, CT_RELATIVE_PATH, default_shared_dir, load_second_ct  # noqa: E402

from carmreg.logic.geometry.camera import POSE_NAMES, project  # noqa: E402
from carmreg.logic.geometry.distortion import RadialDistortion  # noqa: E402
from carmreg.logic.image.turn import UNDONE_BY  # noqa: E402
from carmreg.logic.io.atomic import atomic_write_json, atomic_write_text  # noqa: E402
from carmreg.logic.io.landmarks import Landmarks2D  # noqa: E402
from carmreg.logic.io.xray import load_xray  # noqa: E402
from carmreg.logic.registration.labellings import shifted_labels  # noqa: E402
from carmreg.logic.registration.pipeline import CarmRegLogic  # noqa: E402
from carmreg.logic.registration.state import RegistrationParameters  # noqa: E402
from carmreg.logic.resources import sample_case  # noqa: E402
from carmreg.logic.simulation.evaluation import evaluate  # noqa: E402
from carmreg.logic.simulation.options import SimulationOptions  # noqa: E402

MODES = ("unnamed", "named", "wrong", "none")
STATUSES = ("confident", "ambiguous", "contradicted", "proposed")
RESULTS = "results_appearance"


def half(case: int) -> str:
    return "tune" if case % 2 == 0 else "report"


# ----------------------------------------------------------------------------------------------- cases

class CaseMaker:
    """Builds the scenes of a case (both detectors planned, those asked for rendered) from the CTs, once per case."""

    KEPT_CASES = 4

    def __init__(self, second_ct: bool = True, depth_range_mm: float = SimulationOptions.depth_range_mm):
        """``second_ct`` False: the chest CT only (a test that needs no ../shared); ``depth_range_mm``: the source's
        depth drawn within this of the nominal (``app.draw_pose_and_motion``)."""
        self.depth_range_mm = depth_range_mm
        sample = sample_case()
        self.cts = {"chest": (load_case(), Path(sample["ct"]), Path(sample["ct_landmarks"]))}
        self.parts = {}
        self._plans: dict[int, tuple[dict, dict]] = {}  # case -> (every detector's plan, the scenes rendered)
        second = load_second_ct() if second_ct else None
        if second is not None:
            self.cts["abdomen"] = (second, default_shared_dir() / CT_RELATIVE_PATH, CENTROIDS_PATH)
        elif second_ct:
            print("bench_appearance: the second CT (../shared) is not found: every case uses the chest CT",
                  file=sys.stderr, flush=True)

    def ct_name(self, case: int) -> str:
        return "abdomen" if "abdomen" in self.cts and case % 3 == 2 else "chest"

    def scenes(self, case: int, detectors: set[str]) -> dict[str, app.Scene]:
        """The case's scene on each of ``detectors`` (a new pose is drawn until every detector shows 3 adjacent
        levels). The scenes of every detector are planned (``app.plan_scene``), in one order, whichever are asked
        for: they draw from one random stream, so a case run with some of its variants gets the images it gets with
        all of them. Only the detectors asked for are rendered (``app.render_scene``: the renders draw nothing at
        random, so the images are the same either way; a detector's renders are most of a scene's cost). Planned
        once per case and kept, with the scenes rendered, for the ``KEPT_CASES`` latest cases (a scene is only
        read: every variant renders its own image from it)."""
        if case not in self._plans:
            while len(self._plans) >= self.KEPT_CASES:
                del self._plans[next(iter(self._plans))]
            self._plans[case] = (self._every_plan(case), {})
        plans, rendered = self._plans[case]
        name = self.ct_name(case)
        (ct, labels, _), _, _ = self.cts[name]
        for d in sorted(set(detectors) - set(rendered)):
            rendered[d] = app.render_scene(plans[d], ct, labels, self.parts[name])
        return {d: rendered[d] for d in detectors}

    def _every_plan(self, case: int) -> dict[str, app.ScenePlan]:
        name = self.ct_name(case)
        (ct, labels, centroids), _, _ = self.cts[name]
        if name not in self.parts:
            self.parts[name] = app.split_mu(ct.hu)
        rng = np.random.default_rng(7000 + case)
        for _ in range(20):
            pose, motions = app.draw_pose_and_motion(rng, ct, labels, centroids, self.depth_range_mm)
            try:
                return {d: app.plan_scene(name, centroids, pose, motions, app.DETECTORS[d],
                                          app.make_geometry(ct, app.DETECTORS[d]), rng) for d in sorted(app.DETECTORS)}
            except LookupError:
                continue
        raise RuntimeError(f"case {case}: no pose with 3 adjacent visible levels in 20 draws")

    def files(self, case: int) -> tuple[Path, Path, list[str]]:
        """(CT path, CT landmarks path, CT level names) for the command line."""
        name = self.ct_name(case)
        (_, _, centroids), ct_path, lm_path = self.cts[name]
        return ct_path, lm_path, list(centroids.sorted().labels)


def truth_polarity(truth: dict) -> str:
    """The polarity of the image as CarmReg's reader holds it: as displayed, except a MONOCHROME1 DICOM storing
    linear intensity (LIN, sign +1), whose stored intensities the reader keeps since stop 30 (``io.xray``): bone
    dark whatever its display."""
    look = truth.get("look") or {}
    if look.get("file") == "dcm-mono1" and look.get("storage") == "linear":
        return "bone-dark"
    return "bone-bright" if truth["bone_bright_displayed"] else "bone-dark"


def write_variant(scene: app.Scene, variant: app.Variant, case: int, folder: Path) -> dict:
    """Render and store one variant of a case: the X-ray file, truth.json, clicks; returns the case record."""
    base = app.base_look(np.random.default_rng(9000 + case), scene.detector)
    rng = np.random.default_rng([9100 + case, list(app.VARIANTS).index(variant.name)])
    look = app.variant_look(base, variant, rng)
    pixels = app.render(scene, look, rng)
    xray = app.write_xray(folder / "xray", pixels, scene.detector, look)
    truth = app.truth_dict(scene, look.mirrored, look.display_turn)
    truth["look"] = dataclasses.asdict(look)
    truth["bone_bright_displayed"] = look.bone_bright
    atomic_write_json(folder / "truth.json", truth)
    return {"xray": xray, "truth": truth, "look": look}


def prepared_case(maker: CaseMaker, case: int, variant_name: str, folder: Path, cache_dir: str,
                  clicks: bool = True, names=None):
    """(logic, state, truth): one variant of a case written to ``folder`` (``write_variant``) and prepared for an
    in-process registration on the case's CT (no stage run yet; DRR databases cached in ``cache_dir``), with the
    case's clicks (unnamed, or named ``names``: a list, or ``names(truth)``) or, ``clicks`` False, none. The one
    place the benchmark's scripts and tests load a case as ``carmreg register`` would."""
    (ct, _, centroids), _, _ = maker.cts[maker.ct_name(case)]
    variant = app.VARIANTS[variant_name]
    record = write_variant(maker.scenes(case, {variant.detector})[variant.detector], variant, case, folder)
    truth, detector = record["truth"], app.DETECTORS[variant.detector]
    xray = load_xray(record["xray"], sdd_mm=detector.sdd_mm, pixel_spacing_mm=detector.pixel_mm)
    uv_px = np.asarray(truth["clicks_uv_px"] if clicks else np.zeros((0, 2)), float)
    labels = names(truth) if callable(names) else names
    labels = [None] * len(uv_px) if labels is None else list(labels)
    logic = CarmRegLogic()
    state = logic.prepare(ct, centroids, xray, Landmarks2D(labels, uv_px), RegistrationParameters(cache_dir=cache_dir))
    return logic, state, truth


def registered_to_levels(case: int, variant_name: str, cache_dir: str, clicks: bool = True):
    """(state, true pose (6,) in ``POSE_NAMES`` order): one variant of a case prepared (``prepared_case``, in a
    temporary folder, with its unnamed clicks or none) and registered in process up to its levels stage - where the
    diagnostic scripts (``score_true_pose.py``, ``labelling_starts.py``) take it."""
    logic, state, truth = prepared_case(CaseMaker(second_ct=True), case, variant_name, Path(tempfile.mkdtemp()),
                                        cache_dir, clicks=clicks)
    logic.run_through(state, "levels")
    return state, np.array([truth["pose"][k] for k in POSE_NAMES])


def clicks_file(mode: str, truth: dict, ct_labels: list[str], folder: Path, rng) -> tuple[Path | None, list]:
    """(clicks JSON for the mode or None for no clicks, the names given)."""
    uv = truth["clicks_uv_px"]
    if mode == "none":
        return None, []
    if mode == "unnamed":
        doc, given = uv, [""] * len(uv)
    else:
        labels = list(truth["clicked"])
        if mode == "wrong":
            labels = next((s for s in (shifted_labels(labels, k, ct_labels) for k in
                                       ((1, -1) if rng.random() < 0.5 else (-1, 1))) if s is not None), None)
            if labels is None:
                return None, ["<no shift possible>"]
        doc, given = {lb: p for lb, p in zip(labels, uv, strict=True)}, labels
    path = folder / f"clicks_{mode}.json"
    atomic_write_text(path, json.dumps(doc))
    return path, given


# ----------------------------------------------------------------------------------------------- one run

def distortion_args(truth: dict) -> list[str]:
    """``--distortion-mm`` of the scene's pincushion (k r^3 at r = 100 mm), as a calibrated C-arm would give it
    (``--calibrated-distortion``; the centre offset and vertical stretch the scene also has stay unknown); none
    for a scene without one."""
    k = (truth.get("distortion") or {}).get("k_per_mm2")
    return ["--distortion-mm", f"{k * 100.0**3:.4f}"] if k else []


def register(xray: Path, ct: Path, ct_lm: Path, clicks: Path | None, out: Path, detector: app.Detector,
             cache_dir: str, timeout_s: float, extra: tuple = ()) -> tuple[int, float, str]:
    """Run ``carmreg register`` as a subprocess: (exit code, seconds, last stderr line)."""
    cmd = [str(Path(sys.executable).with_name("carmreg")), "register", "--ct", str(ct), "--ct-landmarks",
           str(ct_lm), "--xray", str(xray), "--out", str(out), "--cache-dir", cache_dir, *extra]
    cmd += ["--xray-landmarks", str(clicks)] if clicks is not None else ["--no-clicks"]
    if xray.suffix != ".dcm":
        cmd += ["--sdd-mm", str(detector.sdd_mm), "--pixel-spacing-mm", str(detector.pixel_mm)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        code, err = proc.returncode, proc.stderr
    except subprocess.TimeoutExpired:
        code, err = -9, f"timeout after {timeout_s:.0f} s"
    seconds = time.perf_counter() - t0
    lines = [ln for ln in err.splitlines() if ln.strip()]
    return code, seconds, (lines[-1] if lines else "")[:1000]


def polarity_read(result: dict, xray: Path, detector: app.Detector) -> tuple[str | None, str]:
    """(decided polarity 'bone-dark'/'bone-bright', where from)."""
    app = result.get("appearance") if isinstance(result.get("appearance"), dict) else None
    if app and app.get("polarity") in ("bone-dark", "bone-bright"):
        return app["polarity"], "result.json appearance"
    try:
        x = load_xray(xray, sdd_mm=None if xray.suffix == ".dcm" else detector.sdd_mm,
                      pixel_spacing_mm=None if xray.suffix == ".dcm" else detector.pixel_mm)
    except Exception:  # noqa: BLE001 - a refused file has no polarity
        return None, "file refused"
    return ("bone-dark" if x.bone_dark else "bone-bright"), "assumed by the reader"


def level_offset(P: np.ndarray, centroids: dict, truth: dict) -> int | None:
    """Most common level offset between where the found pose puts each visible level and the true level nearest
    to it (0 = right names)."""
    visible = [lb for lb in centroids if truth["levels"].get(lb, {}).get("visible")]
    if not visible:
        return None
    true_uv = np.array([truth["levels"][lb]["uv_true_px"] for lb in visible])
    offsets = [int(np.argmin(np.linalg.norm(true_uv - project(P, centroids[lb][None])[0], axis=1))) - k
               for k, lb in enumerate(visible)]
    values, counts = np.unique(offsets, return_counts=True)
    return int(values[np.argmax(counts)])


def drawn_through(geometry: dict):
    """Where the result draws a projected point (``RadialDistortion.distort`` of its detector: the pincushion
    given or estimated, result.json ``geometry``); None on a pinhole (or a record without one)."""
    if not geometry.get("distortion_mm"):
        return None
    return RadialDistortion.from_shift(geometry["distortion_mm"], geometry["principal_point_px"],
                                       geometry["pixel_spacing_mm"]).distort


def _hypotheses(level_check: dict) -> list[dict]:
    """Every registered labelling of the run, compactly (labels, score, GC, click mPDE, whether registered, where a
    hopeless refinement stopped): enough to replay a confidence rule on the recorded runs."""
    keys = ("labels", "score", "similarity", "agreement", "mpde_mm", "refined", "stopped_at_evaluations", "starts")
    return [{k: h.get(k) for k in keys} for h in level_check.get("hypotheses") or []]


def score(mode: str, code: int, result: dict | None, truth: dict, given: list, centroids: dict) -> dict:
    """The run's answer against the truth (module docstring)."""
    row: dict = {"exit": code}
    if result is None or "projection_matrix" not in result:
        return {**row, "status": "refused" if code == 2 else "failed", "answer_right": False}
    lc = result.get("level_check") or {}
    row.update(ok=result.get("ok"), status=lc.get("status"), margin=lc.get("margin"),
               assigned=lc.get("assigned_labels"), winner=lc.get("winner_labels"),
               warnings=result.get("warnings", [])[:4], appearance=result.get("appearance"),
               checks=lc.get("checks"), reasons=lc.get("reasons"), hypotheses=_hypotheses(lc))
    stages = {st.get("name"): st for st in result.get("stages", [])}
    row["stage_seconds"] = {k: st.get("seconds") for k, st in stages.items()}
    row["db_from_cache"] = stages.get("database", {}).get("from_cache")
    P = np.asarray(result["projection_matrix"], float)
    clicked = set(truth["clicked"]) if mode != "none" else set()
    ev = evaluate(P, centroids, truth, clicked, shown=drawn_through(result["geometry"]))
    shown = evaluate(np.asarray(truth["projection_matrix"], float), centroids, truth, clicked)
    row.update(unfitted_pde_mm=ev["unfitted_pde_pose_mm"], unfitted_image_mm=ev["unfitted_pde_image_mm"],
               unfitted_true_pose_image_mm=shown["unfitted_pde_image_mm"],
               all_named_correctly=ev["all_named_correctly"], offset=level_offset(P, centroids, truth))
    row["winner_right"] = row["winner"] == truth["clicked"] if mode != "none" else ev["all_named_correctly"]
    if mode == "unnamed":
        row["answer_right"] = row["assigned"] == truth["clicked"]
    elif mode in ("named", "wrong"):
        row["answer_right"] = list(given) == truth["clicked"]
    else:
        row["answer_right"] = bool(ev["all_named_correctly"])
    return row


def run_one(job: dict, cache_dir: str, timeout_s: float) -> dict:
    """One registration, scored; an error of the benchmark itself is recorded as a failed run."""
    try:
        return _run_one(job, cache_dir, timeout_s)
    except Exception as exc:  # noqa: BLE001 - keep a long run going; the row says what broke
        return {"case": job["case"], "half": half(job["case"]), "ct": job["ct_name"], "variant": job["variant"],
                "mode": job["mode"], "seconds": float("nan"), "truth_labels": job["truth"]["clicked"],
                "given": job["given"], "stderr": f"benchmark error: {type(exc).__name__}: {exc}"[:300],
                "exit": None, "status": "failed", "answer_right": False, "polarity": None,
                "polarity_right": None}


def _run_one(job: dict, cache_dir: str, timeout_s: float) -> dict:
    (job["out"] / "result.json").unlink(missing_ok=True)
    code, seconds, err = register(job["xray"], job["ct"], job["ct_lm"], job["clicks"], job["out"], job["detector"],
                                  cache_dir, timeout_s, job.get("register_args", ()))
    result = None
    result_path = job["out"] / "result.json"
    if code in (0, 1) and result_path.is_file():
        result = json.loads(result_path.read_text())
        if job.get("turned") and "projection_matrix" in result:
            result = as_stored(result, job["turned"])
    row = {"case": job["case"], "half": half(job["case"]), "ct": job["ct_name"], "variant": job["variant"],
           "mode": job["mode"], "seconds": seconds, "truth_labels": job["truth"]["clicked"], "given": job["given"],
           "stderr": err if code not in (0, 1) else ""}
    if job.get("turned"):
        row["turned"] = job["turned"]
    row.update(score(job["mode"], code, result, job["truth"], job["given"], job["centroids"]))
    decided, source = polarity_read(result or {}, job["xray"], job["detector"]) if result else (None, "no result")
    truth_pol = truth_polarity(job["truth"])
    row.update(polarity=decided, polarity_source=source, polarity_truth=truth_pol,
               polarity_right=None if decided is None else decided == truth_pol)
    return row


# ----------------------------------------------------------------------------------------------- summary

def _pct(values, q) -> str:
    return f"{np.percentile(values, q):.2f}" if len(values) else "-"


def summarize(rows: list[dict], which: str = "report") -> str:
    """Markdown tables of the ``which`` half ('report', 'tune' or 'all')."""
    sel = [r for r in rows if which == "all" or r["half"] == which]
    if not sel:
        return f"**{which} half**: no runs yet.\n"
    cases = sorted({(r["case"], r["ct"]) for r in sel})
    by_ct = {ct: sum(c[1] == ct for c in cases) for ct in sorted({c[1] for c in cases})}
    variants = [v for v in app.VARIANTS if any(r["variant"] == v for r in sel)]
    modes = [m for m in MODES if any(r["mode"] == m for r in sel)]
    lines = [f"**{which} half**: {len(cases)} cases ({', '.join(f'{k} {v}' for k, v in by_ct.items())}), "
             f"{len(variants)} variants, modes {', '.join(modes)}; {len(sel)} runs of `carmreg register`.", ""]
    lines += ["| variant | mode | n | answer right | CONFIDENT (no clicks: proposed) and wrong | ambiguous | "
              "contradicted | refused / failed | polarity right | s per run, median (max) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for v in variants:
        for m in modes:
            runs = [r for r in sel if r["variant"] == v and r["mode"] == m]
            if runs:
                lines.append(_row(v, m, runs))
    lines += ["", "Reliability (all modes): status against the answer's labels, right / wrong.", "",
              "| variant | " + " | ".join(STATUSES) + " | refused / failed |", "|---|" + "---|" * (len(STATUSES) + 1)]
    for v in variants + ["**all**"]:
        runs = [r for r in sel if r["variant"] == v or v == "**all**"]
        cells = [f"{sum(r['status'] == s and r['answer_right'] for r in runs)} / "
                 f"{sum(r['status'] == s and not r['answer_right'] for r in runs)}" for s in STATUSES]
        bad = sum(r["status"] in ("refused", "failed") for r in runs)
        lines.append(f"| {v} | " + " | ".join(cells) + f" | {bad} |")
    lines += ["", "Per CT (all variants): unnamed clicks named right; CONFIDENT (no clicks: proposed) and wrong in "
              "any mode.", "", "| CT | unnamed right | CONFIDENT (no clicks: proposed) and wrong |", "|---|---|---|"]
    for ct in by_ct:
        unnamed = [r for r in sel if r["ct"] == ct and r["mode"] == "unnamed"]
        bad = sum(r["status"] in ("confident", "proposed") and not r["answer_right"] for r in sel if r["ct"] == ct)
        lines.append(f"| {ct} | {sum(r['answer_right'] for r in unnamed)} / {len(unnamed)} | {bad} |")
    flipped = [r for r in sel if app.VARIANTS[r["variant"]].changes.get("mirrored") and not r.get("turned")]
    if flipped:
        lines += ["", f"Mirrored display: {sum(r['status'] == 'confident' for r in flipped)} of {len(flipped)} "
                  "runs CONFIDENT (issue 11: a flipped image is detected and registered, or refused; never named "
                  "with confidence)."]
    for turn in app.DISPLAY_TURNS[1:]:
        runs = [r for r in sel if app.VARIANTS[r["variant"]].changes.get("display_turn") == turn]
        if runs:
            wrong = sum(r["status"] in ("confident", "proposed") and not r["answer_right"] for r in runs)
            early = [r for r in runs if _refused_for_the_clicks(r)]
            lines += ["", f"Display {turn}: {sum(r['status'] == 'confident' for r in runs)} of {len(runs)} runs "
                      f"CONFIDENT, {wrong} CONFIDENT (no clicks: proposed) and wrong; refused as a display turned "
                      f"(no level named): {sum(_refused_display(r) for r in runs)}; refused before any stage for "
                      f"their clicks (head-down or across the image): {len(early)}, naming the turn back "
                      f"({UNDONE_BY[turn]}) {sum(UNDONE_BY[turn] in r['stderr'] for r in early)}."]
    turned = [r for r in sel if r.get("turned")]
    if turned:
        wrong = sum(r["status"] in ("confident", "proposed") and not r["answer_right"] for r in turned)
        lines += ["", f"Mirrored display registered turned back (`--orient-xray {MIRROR_TURN}`): answer right in "
                  f"{sum(bool(r['answer_right']) for r in turned)} of {len(turned)} runs, "
                  f"{sum(r['status'] == 'confident' for r in turned)} CONFIDENT, {wrong} CONFIDENT (no clicks: "
                  "proposed) and wrong."]
    lines += _targets(sel)
    lines += ["", "Levels not clicked: pose-PDE, found vs true pose (detector mm), modes unnamed + named.", "",
              "| variant | levels | median | 95th pct | max | within 5 mm |", "|---|---|---|---|---|---|"]
    for v in variants + ["**all**"]:
        vals = _unfitted([r for r in sel if r["variant"] == v or v == "**all**"])
        if len(vals):
            lines.append(f"| {v} | {len(vals)} | {np.median(vals):.2f} | {_pct(vals, 95)} | {vals.max():.2f} | "
                         f"{np.mean(vals < 5) * 100:.0f} % |")
    lines += _image_pde_table(sel, variants)
    secs = [r["seconds"] for r in sel if _timed(r)]
    if secs:
        built = sum(r.get("db_from_cache") is False for r in sel)
        lines += ["", f"Time per run (the whole `carmreg register` process, database cached; {built} runs that "
                  f"built a database left out): median {np.median(secs):.1f} s, max {max(secs):.1f} s over "
                  f"{len(secs)} runs, on a machine shared with other work."]
    return "\n".join(lines) + "\n"


def shown_as_acquired(variant_name: str) -> bool:
    """Whether the variant's display is neither mirrored nor turned (``appearance.display_map``). A mirrored or turned
    display is never to be named as stored, so the issue's targets but the first two leave it out."""
    changes = app.VARIANTS[variant_name].changes
    return not changes.get("mirrored") and changes.get("display_turn", "none") == "none"


def _refused_display(row: dict) -> bool:
    """Whether the run's X-ray was refused for its display: matched best mirrored or turned (result.json
    ``appearance.orientation``, ``outcome.refused_display``)."""
    return (row.get("appearance") or {}).get("orientation", "as-stored") != "as-stored"


def _refused_for_the_clicks(row: dict) -> bool:
    """Whether the run was refused before any stage for its clicks' course (``preflight.head_down``, ``across``): exit
    code 2 with a turn advised."""
    return row.get("exit") == 2 and "--orient-xray" in (row.get("stderr") or "")


def _unfitted(runs: list[dict]) -> np.ndarray:
    """Levels not clicked, pose-PDE found vs true pose (detector mm), of the runs with clicks (unnamed, named)."""
    return np.concatenate([r["unfitted_pde_mm"] for r in runs if r["mode"] in ("unnamed", "named")
                           and r.get("unfitted_pde_mm")] or [[]])


def _targets(sel: list[dict]) -> list[str]:
    """The issue's targets on these runs, in its own terms: every variant for confident wrong answers; the correctly
    displayed variants (a mirrored display is never to be named) for the rest; levels not clicked split by the
    image's polarity and by detector."""
    shown = [r for r in sel if shown_as_acquired(r["variant"])]
    named = [r for r in shown if r["mode"] == "named"]
    unnamed = [r for r in shown if r["mode"] == "unnamed"]
    off = [r for r in sel if r["mode"] == "wrong"]
    wrong = sum(r["status"] in ("confident", "proposed") and not r["answer_right"] for r in sel)
    pol = [r for r in sel if r.get("polarity_right") is not None]

    def levels(keep) -> str:
        vals = _unfitted([r for r in shown if keep(r["variant"])])
        return f"{np.median(vals):.2f} / {_pct(vals, 95)} mm ({len(vals)})" if len(vals) else "-"
    return ["", "The issue's targets on these runs (mirrored and turned displays left out of all but the first "
            "two):", "",
            f"- CONFIDENT (no clicks: proposed) and wrong: {wrong} of {len(sel)} runs; names one level off "
            f"CONFIDENT: {sum(r['status'] == 'confident' for r in off)} of {len(off)}",
            f"- unnamed clicks named right: {sum(r['answer_right'] for r in unnamed)} / {len(unnamed)} "
            f"({sum(r['answer_right'] and r['status'] == 'confident' for r in unnamed)} confident); right names "
            f"flagged (not confident): {sum(r['status'] != 'confident' for r in named)} / {len(named)}",
            f"- polarity right: {sum(r['polarity_right'] for r in pol)} / {len(pol)}",
            "- levels not clicked, median / 95th (levels): all " + levels(lambda v: True)
            + "; bone dark " + levels(lambda v: "-dark-" in v) + "; bone bright " + levels(lambda v: "-bright-" in v)
            + "; flat panel " + levels(lambda v: v.startswith("fp-"))
            + "; intensifier without a calibration " + levels(lambda v: v.startswith("ii-"))]


def _image_pde_table(sel: list[dict], variants: list[str]) -> list[str]:
    """Levels not clicked, where the X-ray shows them: |P_found X - uv_true| against |P_true X - uv_true| (the
    vertebra's image position after per-level motion and the pincushion; ``evaluate``'s ``pde_image_mm``). On an
    uncalibrated intensifier a pinhole pose that absorbs the pincushion is off the true pose (pose-PDE) yet may
    draw the names closer to the vertebrae than the true pose would; the second pair is that floor."""
    lines = ["", "Levels not clicked, where the X-ray shows them (image-PDE, detector mm: the level's name as drawn "
             "against where its moved vertebra shows, pincushion included), modes unnamed + named; the true pose "
             "drawn the same way (per-level motion and the pincushion alone).", "",
             "| variant | levels | found pose: median | 95th pct | true pose: median | 95th pct |",
             "|---|---|---|---|---|---|"]
    for v in variants + ["**all**"]:
        runs = [r for r in sel if (r["variant"] == v or v == "**all**") and r["mode"] in ("unnamed", "named")
                and r.get("unfitted_image_mm")]
        found = np.concatenate([r["unfitted_image_mm"] for r in runs] or [[]])
        true = np.concatenate([r["unfitted_true_pose_image_mm"] for r in runs] or [[]])
        if len(found):
            lines.append(f"| {v} | {len(found)} | {np.median(found):.2f} | {_pct(found, 95)} | "
                         f"{np.median(true):.2f} | {_pct(true, 95)} |")
    return lines


def _timed(r: dict) -> bool:
    """A run whose time counts: it registered (not refused) with the database from the cache."""
    return r["status"] != "refused" and np.isfinite(r["seconds"]) and r.get("db_from_cache") is not False


def _row(variant: str, mode: str, runs: list[dict]) -> str:
    n = len(runs)
    right = sum(r["answer_right"] for r in runs)
    conf_wrong = sum(r["status"] in ("confident", "proposed") and not r["answer_right"] for r in runs)
    amb = sum(r["status"] == "ambiguous" for r in runs)
    contra = sum(r["status"] == "contradicted" for r in runs)
    bad = sum(r["status"] in ("refused", "failed") for r in runs)
    pol = [r for r in runs if r.get("polarity_right") is not None]
    assumed = any(r.get("polarity_source") == "assumed by the reader" for r in pol)
    pol_txt = f"{sum(r['polarity_right'] for r in pol)} / {len(pol)}{' (assumed)' if assumed else ''}" if pol else "-"
    secs = [r["seconds"] for r in runs if _timed(r)]
    t = f"{np.median(secs):.1f} ({max(secs):.1f})" if secs else "-"
    return (f"| {variant} | {mode} | {n} | {right} | {'**' + str(conf_wrong) + '**' if conf_wrong else 0} | {amb} | "
            f"{contra} | {bad} | {pol_txt} | {t} |")


def write_results(out: Path, rows: list[dict], meta: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / f"{RESULTS}.json", {"meta": meta, "runs": rows})
    notes = "\n".join(f"- `{v.name}`: {v.note}" for v in app.VARIANTS.values())
    run = (f"Method: CarmReg's code (Logic/, CarmRegModule/) as of commit {meta.get('commit') or '?'}; run "
           f"`bench_appearance.py "
           f"{meta.get('command', '')}`; {meta.get('machine', '')}, {meta.get('date', '')}.")
    text = (f"# Appearance benchmark (issue 11, item 4)\n\n{meta['description']}\n\n{run}\n\nVariants:\n{notes}\n\n"
            + summarize(rows, "report") + "\n" + summarize(rows, "tune"))
    atomic_write_text(out / f"{RESULTS}.md", text)


# ----------------------------------------------------------------------------------------------- main

def jobs_for_case(maker: CaseMaker, case: int, variants: list[str], modes: list[str], done: set, work: Path,
                  calibrated: bool = False, turn_mirrored: bool = False) -> list[dict]:
    """The runs of one case still to do; ``calibrated``: each is given its scene's pincushion (``distortion_args``);
    ``turn_mirrored``: a mirrored display is registered turned back (``--orient-xray``, as a user told by the
    refusal would), its result scored in the stored frame (``as_stored``)."""
    todo = [(v, m) for v in variants for m in modes if (case, v, m) not in done]
    if not todo:
        return []
    scenes = maker.scenes(case, {app.VARIANTS[v].detector for v, _ in todo})
    ct_path, lm_path, ct_labels = maker.files(case)
    (_, _, centroids), _, _ = maker.cts[maker.ct_name(case)]
    jobs = []
    for v in dict.fromkeys(v for v, _ in todo):
        folder = work / f"case{case:03d}" / v
        made = write_variant(scenes[app.VARIANTS[v].detector], app.VARIANTS[v], case, folder)
        rng = np.random.default_rng(9500 + case)
        for m in modes:
            if (case, v, m) in done:
                continue
            clicks, given = clicks_file(m, made["truth"], ct_labels, folder, rng)
            if m != "none" and clicks is None:
                continue
            jobs.append({"case": case, "ct_name": maker.ct_name(case), "variant": v, "mode": m,
                         "xray": made["xray"], "ct": ct_path, "ct_lm": lm_path, "clicks": clicks,
                         "out": folder / f"out_{m}", "detector": scenes[app.VARIANTS[v].detector].detector,
                         "truth": made["truth"], "given": given, "centroids": centroids.as_dict(),
                         "register_args": distortion_args(made["truth"]) if calibrated else []})
            if turn_mirrored and app.VARIANTS[v].changes.get("mirrored"):
                jobs[-1].update(turned=MIRROR_TURN, register_args=[*jobs[-1]["register_args"], "--orient-xray",
                                                                   MIRROR_TURN])
    return jobs


MIRROR_TURN = "mirrored-left-right"


def as_stored(result: dict, turn: str) -> dict:
    """A result registered on the X-ray turned by ``turn`` (``--orient-xray``; only the mirror, its own inverse)
    with its projection matrix and principal point taken back to the image as stored, where the truth is:
    u_stored = (columns - 1) - u_turned, i.e. P_stored = F P with F = [[-1, 0, columns - 1], [0, 1, 0], [0, 0, 1]]."""
    assert turn == MIRROR_TURN, turn
    geometry = dict(result["geometry"])
    cols = geometry["size_px"][0]
    flip = np.array([[-1.0, 0.0, cols - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    u0, v0 = geometry["principal_point_px"]
    geometry["principal_point_px"] = [cols - 1.0 - u0, v0]
    return {**result, "geometry": geometry,
            "projection_matrix": (flip @ np.asarray(result["projection_matrix"], float)).tolist()}


def rescore(rows: list[dict], work: Path) -> list[dict]:
    """Score every run again from its stored result.json and truth.json (after a change of the scoring); the
    measured seconds, exit code and messages are kept. Runs whose files are gone are kept as they were."""
    sample = sample_case()
    landmarks = {"chest": Path(sample["ct_landmarks"]), "abdomen": CENTROIDS_PATH}
    from carmreg.logic.io.landmarks import read_landmarks_3d

    centroids = {ct: read_landmarks_3d(p).sorted().as_dict() for ct, p in landmarks.items() if p.is_file()}
    out = []
    for r in rows:
        folder = work / f"case{r['case']:03d}" / r["variant"]
        result_path, xrays = folder / f"out_{r['mode']}" / "result.json", sorted(folder.glob("xray.*"))
        if not (folder / "truth.json").is_file() or not xrays or r["ct"] not in centroids:
            out.append(r)
            continue
        truth = json.loads((folder / "truth.json").read_text())
        result = json.loads(result_path.read_text()) if result_path.is_file() and r.get("exit") in (0, 1) else None
        if result is not None and r.get("turned") and "projection_matrix" in result:
            result = as_stored(result, r["turned"])
        new = {k: r[k] for k in ("case", "half", "ct", "variant", "mode", "seconds", "truth_labels", "given",
                                 "stderr")}
        new.update({"turned": r["turned"]} if r.get("turned") else {})
        new.update(score(r["mode"], r.get("exit"), result, truth, r["given"], centroids[r["ct"]]))
        detector = app.DETECTORS[app.VARIANTS[r["variant"]].detector]
        decided, source = polarity_read(result, xrays[0], detector) if result else (None, "no result")
        truth_pol = truth_polarity(truth)
        new.update(polarity=decided, polarity_source=source, polarity_truth=truth_pol,
                   polarity_right=None if decided is None else decided == truth_pol)
        out.append(new)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=24)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--half", choices=("all", "tune", "report"), default="all",
                        help="only the cases of this half (tune = even index, report = odd)")
    parser.add_argument("--ct", choices=("any", "chest", "abdomen"), default="any",
                        help="only the cases of this CT (abdomen = the second CT: case index %% 3 == 2)")
    parser.add_argument("--variants", default=",".join(app.VARIANTS))
    parser.add_argument("--modes", default="unnamed,named,wrong")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    parser.add_argument("--jobs", type=int, default=1, help="registrations run at once (the machine is shared)")
    parser.add_argument("--cache-dir", default="/tmp/carmreg-bench-cache")
    parser.add_argument("--work", type=Path, default=Path("/tmp/carmreg-appearance"), help="case files")
    parser.add_argument("--timeout-s", type=float, default=900.0)
    parser.add_argument("--calibrated-distortion", action="store_true",
                        help="give every intensifier case its pincushion coefficient (--distortion-mm), as a "
                        "calibrated C-arm would")
    parser.add_argument("--turn-mirrored", action="store_true",
                        help="register the mirrored displays turned back (--orient-xray mirrored-left-right), as "
                        "the refusal tells a user to")
    parser.add_argument("--depth-range-mm", type=float, default=SimulationOptions.depth_range_mm,
                        help="draw the source's depth within this of the nominal (the same scenes, nearer or "
                        "farther; the default is the benchmark's)")
    parser.add_argument("--runs", type=Path,
                        help="run exactly these, in this order, instead of --first/--cases/--variants/--modes: a "
                        "JSON list of [case, variant, mode], or a results JSON whose runs are taken (a re-run of "
                        "recorded runs, or a quiet timing pass in a recorded order)")
    parser.add_argument("--summary-only", action="store_true", help="rewrite the tables from the JSON")
    parser.add_argument("--rescore", action="store_true",
                        help="with --summary-only: score the runs again from the result.json files under --work")
    args = parser.parse_args(argv)
    variants = [v for v in args.variants.split(",") if v]
    modes = [m for m in args.modes.split(",") if m]
    unknown = [v for v in variants if v not in app.VARIANTS] + [m for m in modes if m not in MODES]
    if unknown:
        print(f"bench_appearance: error: unknown variant or mode {', '.join(unknown)}; variants: "
              f"{', '.join(app.VARIANTS)}; modes: {', '.join(MODES)}", file=sys.stderr)
        return 2
    path = args.out / f"{RESULTS}.json"
    stored = json.loads(path.read_text()) if path.is_file() else {"runs": [], "meta": {}}
    rows = stored["runs"]
    meta = {"machine": f"{platform.processor() or platform.machine()}, 2 cores shared",
            "date": time.strftime("%Y-%m-%d"), "commit": _commit(), "command": " ".join(sys.argv[1:])}
    if args.summary_only:  # the run's own facts stay
        meta.update({k: v for k, v in stored.get("meta", {}).items() if k in meta})
    meta["description"] = _description()
    if args.summary_only:
        if args.rescore:
            rows = rescore(rows, args.work)
        write_results(args.out, rows, meta)
        print(summarize(rows, "report"))
        return 0
    done = {(r["case"], r["variant"], r["mode"]) for r in rows}
    maker = CaseMaker(depth_range_mm=args.depth_range_mm)
    batches = (listed_jobs(maker, _listed(args.runs), done, args) if args.runs is not None
               else case_jobs(maker, variants, modes, done, args))
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        for jobs in batches:
            for row in pool.map(lambda j: run_one(j, args.cache_dir, args.timeout_s), jobs):
                rows.append(row)
                print(f"case {row['case']:3d} {row['ct'][:5]} {row['variant']:<27} {row['mode']:<7} "
                      f"{str(row['status']):<12} {'right' if row['answer_right'] else 'WRONG'} "
                      f"pol {row['polarity']} {row['seconds']:.1f}s {row['stderr'][:80]}", flush=True)
                write_results(args.out, rows, meta)
    print(summarize(rows, "report"))
    return 0


def case_jobs(maker: CaseMaker, variants: list[str], modes: list[str], done: set, args):
    """The runs of ``--first``/``--cases`` (those of ``--half`` and ``--ct``) not yet ``done``, one batch per case
    (``jobs_for_case``), made as they are asked for."""
    for case in range(args.first, args.first + args.cases):
        if (args.half == "all" or half(case) == args.half) and (args.ct == "any" or maker.ct_name(case) == args.ct):
            yield jobs_for_case(maker, case, variants, modes, done, args.work, args.calibrated_distortion,
                                args.turn_mirrored)


def _listed(path: Path) -> list[tuple]:
    """``--runs``: (case, variant, mode) in order, from a JSON list of them or a results JSON's runs."""
    doc = json.loads(path.read_text())
    runs = doc["runs"] if isinstance(doc, dict) else doc
    return [(r["case"], r["variant"], r["mode"]) if isinstance(r, dict) else tuple(r) for r in runs]


def listed_jobs(maker: CaseMaker, keys: list[tuple], done: set, args) -> list[list[dict]]:
    """The runs ``keys`` (``_listed``) not yet ``done``, each as a batch of one, in the listed order (each case's
    files written once)."""
    jobs = {}
    for case in dict.fromkeys(k[0] for k in keys):
        mine = [k for k in keys if k[0] == case]
        for j in jobs_for_case(maker, case, list(dict.fromkeys(k[1] for k in mine)),
                               list(dict.fromkeys(k[2] for k in mine)), done, args.work, args.calibrated_distortion,
                               args.turn_mirrored):
            jobs[(j["case"], j["variant"], j["mode"])] = j
    return [[jobs[k]] for k in keys if k in jobs]


def _description() -> str:
    return ("Each case: a pose and per-level motion drawn as bench_levels draws them, rendered on an image "
            "intensifier (960 px, 0.25 mm, pincushion, circular field) and a flat panel (768 px, 0.388 mm, "
            "rectangular collimation), every variant's appearance made by `Testing/Benchmarks/appearance.py` "
            "(written independently of CarmReg's simulator), stored as a real file and registered by `carmreg "
            "register` as a subprocess (database cached). 'answer right': unnamed = the labels CarmReg assigned are "
            "the true ones; named / wrong = the names given are right (always / never), so every confident 'wrong' "
            "run is a wrong name passed as confident; none = every visible level named right. 'polarity right': "
            "from result.json's `appearance.polarity` when present, else '(assumed)' = what the reader assumed. "
            "Even cases = tune half, odd = report half.")


def _commit() -> str:
    """The last commit that changed the method's code (Logic/, CarmRegModule/)."""
    try:
        root = Path(__file__).resolve().parents[2]
        return subprocess.run(["git", "-C", str(root), "log", "-1", "--format=%h", "--", "Logic", "CarmRegModule"],
                              capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


if __name__ == "__main__":
    sys.exit(main())
