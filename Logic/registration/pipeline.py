"""The logic class: the three-stage registration, orchestrated (method paper 3.1.6 and 3.2).

``CarmRegLogic`` is what the CLI, the GUI and the headless tests drive. It takes explicit arguments, raises
``CarmRegError`` on bad input, reports progress through ``progress(stage, fraction, message)`` and honours
``cancel()`` between steps (``CancelledError``).

Stages (each a plain function in its own module, returning a small result):
  database  - DRRs of the 4 mm mu level over a (ty, tz) grid at tx = 0 (``database``, Algorithm 1), cached;
  spatial   - the X-ray's polarity, storage and orientation decided against the CT (``appearance_checks``), then
              similarity of the coarse X-ray with every DRR -> (ty, tz) (``spatial_search``, Algorithm 2);
  levels    - beyond the paper: which vertebra is which (``level_identify``). Every plausible labelling of the
              clicks (unnamed clicks: every run of consecutive CT levels; named clicks: the names and the names
              shifted +-1, +-2 levels) is registered and scored by image similarity and landmark fit; the
              winner names unnamed clicks, and the margin to the runner-up says confident / ambiguous (or
              contradicted, when the surgeon's names lose). Without clicks the spatial map's peaks are refined
              on the image alone and the levels in view are named;
  depth     - intervertebral distances -> tx, magnification (``depth_search``, Algorithm 3);
  fine      - anchored CMA-ES on the mPDE -> 6-DOF pose (``fine_search``, Algorithm 4);
  refine    - beyond the paper: 6-DOF CMA-ES on gradient correlation with a landmark term
              (``intensity_refine``), a wide coarse pass (4 mm; reused from the levels stage, which ran the
              same computation for the chosen labelling; with clicks also run from their fit at the nominal
              depth, ``labelling_fit.refit_at_nominal_depth``, the better kept) then a local one (3 mm); it fixes
              the out-of-plane rotations and the magnification that three nearly collinear clicks cannot; its pose
              is kept only if the clicks still agree with it. On a round field without a distortion calibration
              the local pass also estimates the intensifier's pincushion (``pincushion``: the pass at fixed
              shifts, the best kept);
  final_drr - DRR of the full-resolution CT at the final pose on the X-ray's detector (``final_drr_detector``).

Geometry: the nominal AP C-arm has its isocentre at the CT volume centre (paper 3.1.3) and its source at
``sod_mm`` from it (the X-ray's DICOM DistanceSourceToPatient when known, else 0.6 x SDD: ``camera.nominal_geometry``).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.errors import CancelledError, RegistrationError
from carmreg.logic.geometry.camera import CarmIntrinsics, CarmPose, nominal_geometry
from carmreg.logic.geometry.projection_distance import mpde_mm
from carmreg.logic.geometry.volume import MuPyramid, Volume
from carmreg.logic.image.appearance import POLARITY_SETTINGS
from carmreg.logic.image.field import FIELDS, exposed_field, field_mask, round_field
from carmreg.logic.image.prepare import (
    EQUALISED,
    STORAGE_SETTINGS,
    attenuation,
    bin_image_to,
    bin_mask_to,
    coarse_factor,
)
from carmreg.logic.io.array_cache import ArrayCache
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D, Pairs
from carmreg.logic.io.xray import XrayImage
from carmreg.logic.registration.appearance_checks import AppearanceChecks
from carmreg.logic.registration.database import build_database, grid
from carmreg.logic.registration.depth import depth_search
from carmreg.logic.registration.fine import fine_search
from carmreg.logic.registration.image_refine import intensity_refine
from carmreg.logic.registration.image_starts import image_starts
from carmreg.logic.registration.labelling_fit import (
    FitContext,
    LabellingFit,
    refit_at_nominal_depth,
    refit_from,
    state_context,
    unshaded_context,
)
from carmreg.logic.registration.labellings import ct_level_names
from carmreg.logic.registration.levels import (
    IdentifyParameters,
    LevelIdentification,
    OpenContest,
    finish_contest,
    identify_from_image,
    open_contest,
)
from carmreg.logic.registration.outcome import build_result
from carmreg.logic.registration.pincushion import (
    UNCORRECTED_INTENSIFIER,
    PincushionEstimate,
    estimate_pincushion,
    grid_for,
    with_shift,
)
from carmreg.logic.registration.preflight import MIN_CLICKS, check_landmarks, given_pairs, preflight
from carmreg.logic.registration.sanity import check_ct_content, check_xray_content
from carmreg.logic.registration.spatial import spatial_search
from carmreg.logic.registration.state import (
    STAGES,
    RegistrationParameters,
    RegistrationResult,
    RegistrationState,
    StageResult,
    chosen_fit,
    drop_results_from,
    initial_appearance,
)
from carmreg.logic.similarity.metrics import METRICS

__all__ = ["MIN_CLICKS", "STAGES", "CarmRegLogic", "RegistrationParameters", "RegistrationResult", "StageResult"]


def final_drr_detector(intr: CarmIntrinsics, sod_mm: float, ct_spacing_mm: float, max_px: int,
                       rays_per_voxel: float) -> CarmIntrinsics:
    """The detector the final DRR is traced on: the X-ray's (``intr``), scaled down (``scaled_to``) until its
    longest side is at most ``max_px`` and its pixel's footprint at the isocentre, ``pixel_mm * sod_mm / sdd_mm``,
    is at least ``ct_spacing_mm / rays_per_voxel`` (the CT's finest voxel spacing, mm); the DRR is then
    interpolated linearly to the X-ray's pixels. More rays per voxel trace the same voxels again and add time, not
    detail: the sample's 1 mm voxels under 0.15 mm pixel footprints were crossed by ~7 x 7 rays each (0.6 s here
    for the chest CT on a 960 x 960 detector; ~0.05 s at 2 rays per voxel). ``intr`` itself when no scaling is
    needed."""
    cols, rows = intr.size_px
    footprint_mm = float(min(intr.pixel_spacing_mm)) * sod_mm / intr.sdd_mm
    scale = min(1.0, max_px / max(cols, rows), footprint_mm * rays_per_voxel / ct_spacing_mm)
    if scale >= 1.0:
        return intr
    return intr.scaled_to((max(1, int(round(cols * scale))), max(1, int(round(rows * scale)))))


def ideal_clicks(clicks, intr: CarmIntrinsics):
    """The clicks where a pinhole camera would put them (``geometry.distortion``: the X-ray's radial distortion
    undone), so that every stage compares them with ``P``; ``build_result`` reports them as clicked. ``clicks``:
    any dataclass with ``uv_px`` (``Landmarks2D``, ``Pairs``), returned itself when the detector has no
    distortion."""
    if not intr.distortion_mm:
        return clicks
    return dataclasses.replace(clicks, uv_px=intr.distortion.undistort(clicks.uv_px))


def _pair_arrays(pairs) -> tuple[np.ndarray, np.ndarray]:
    """(CT points (n, 3) LPS mm, X-ray clicks (n, 2) px) of ``pairs``; empty without pairs (no clicks)."""
    if pairs is None:
        return np.zeros((0, 3)), np.zeros((0, 2))
    return pairs.points_lps_mm, pairs.uv_px


def distortion_given(intr: CarmIntrinsics) -> bool:
    """Whether the detector's distortion was given (a calibration, or 0 for a pinhole camera: ``--distortion-mm``),
    not left at the reader's default (its source then says "default"; none recorded is none given)."""
    return bool(intr.distortion_mm) or not intr.sources.get("distortion_mm", "default").startswith("default")


def pincushion_unknown(state: RegistrationState) -> bool:
    """Whether the refine stage estimates the X-ray's pincushion from the image (``pincushion``): asked
    (``estimate_pincushion``), a round field (an image intensifier's) and no distortion given."""
    return bool(state.parameters.estimate_pincushion and state.round_field
                and not distortion_given(state.geometry.intrinsics))


def take_pincushion(state: RegistrationState, estimate: PincushionEstimate) -> None:
    """The detector from now on has the estimated pincushion (``estimate.shift_mm``; 0: none found, the pinhole
    kept): the geometry (its source ``pincushion.FROM_IMAGE``), the pairs' clicks taken to their ideal points
    (``ideal_clicks``) and the warning on the round field replaced by the estimate's note. ``state.pinhole`` keeps
    what they were (``drop_results_from`` restores them)."""
    note = estimate.note()
    state.pinhole = (state.geometry, state.pairs, note)
    state.warnings[:] = [note if w == UNCORRECTED_INTENSIFIER else w for w in state.warnings]
    state.geometry = with_shift(state.geometry, estimate.shift_mm)
    if state.pairs is not None:
        state.pairs = ideal_clicks(state.pairs, state.geometry.intrinsics)


class CarmRegLogic:
    """Headless logic class: ``register(...)``, or ``prepare(...)`` then ``run_stage(state, name)`` or
    ``run_through(state, last)``."""

    def __init__(self, progress=None):
        self.progress = progress
        self._cancel = False
        self._appearance = AppearanceChecks(self._report, self._check_cancel)  # the spatial stage's first step

    # ------------------------------------------------------------------ control
    def cancel(self) -> None:
        self._cancel = True

    def _check_cancel(self) -> None:
        if self._cancel:
            self._cancel = False
            raise CancelledError("registration cancelled by the user")

    def _report(self, stage: str, fraction: float, message: str = "") -> None:
        self._check_cancel()
        if self.progress is not None:
            self.progress(stage, float(fraction), message)

    # ------------------------------------------------------------------ setup
    def prepare(self, ct: Volume, ct_landmarks: Landmarks3D, xray: XrayImage, xray_landmarks: Landmarks2D,
                parameters: RegistrationParameters | None = None) -> RegistrationState:
        """Validate inputs and set up geometry, pyramid and the attenuation image; no stage is run."""
        self._cancel = False
        params = parameters or RegistrationParameters()
        intrinsics = xray.require_intrinsics()
        if intrinsics.size_px != xray.size_px:
            raise RegistrationError(f"the geometry's detector size {intrinsics.size_px} px differs from the "
                                    f"X-ray image {xray.size_px} px; check the pixel spacing and image")
        check_xray_content(xray.pixels, xray.source)
        check_ct_content(ct.hu, ct.source)
        preflight(ct_landmarks, xray_landmarks, xray_size_px=xray.size_px).raise_first()
        check_landmarks(ct, ct_landmarks, xray, xray_landmarks)
        xray_landmarks = ideal_clicks(xray_landmarks, intrinsics)
        pairs, notes = given_pairs(ct_landmarks, xray_landmarks)
        geometry = nominal_geometry(intrinsics, ct, xray.sod_mm)
        for what, value, settings in (("polarity", params.polarity, POLARITY_SETTINGS),
                                      ("storage", params.storage, STORAGE_SETTINGS),
                                      ("field", params.xray_field, FIELDS)):
            if value not in settings:
                raise RegistrationError(f"{what} {value!r}: use {', '.join(settings[:-1])} or {settings[-1]}")
        found = field_mask(xray.pixels)
        mask, round_ = exposed_field(found, params.xray_field), round_field(found)
        if round_ and not distortion_given(intrinsics):
            notes = [*notes, UNCORRECTED_INTENSIFIER]
        appearance = initial_appearance(xray, params)
        line_integral = attenuation(xray.pixels, mask, appearance.bone_dark, appearance.storage)
        factor = coarse_factor(intrinsics.pixel_spacing_mm, params.coarse_spacing_mm)
        pyramid = MuPyramid(ct, cache=ArrayCache(params.cache_dir) if params.cache_dir else None)
        return RegistrationState(ct, ct_landmarks, xray, xray_landmarks, params, geometry, pairs, pyramid,
                                 line_integral, mask, factor, given_pairs=pairs, warnings=notes,
                                 appearance=appearance, round_field=round_)

    def register(self, ct: Volume, ct_landmarks: Landmarks3D, xray: XrayImage, xray_landmarks: Landmarks2D,
                 parameters: RegistrationParameters | None = None) -> RegistrationResult:
        """Run every stage and return the result (``ok`` False, with reasons, when a check fails)."""
        state = self.prepare(ct, ct_landmarks, xray, xray_landmarks, parameters)
        self.run_through(state)
        return self.result(state)

    def run_through(self, state: RegistrationState, last: str = STAGES[-1]) -> None:
        """Run the stages in order (``STAGES``), the first through ``last``: a registration from ``prepare`` taken as
        far as a script or test needs it (``register`` takes it through every stage)."""
        for name in STAGES[:STAGES.index(last) + 1]:
            self.run_stage(state, name)

    # ------------------------------------------------------------------ stages
    def run_stage(self, state: RegistrationState, name: str) -> StageResult:
        runner = {"database": self._database, "spatial": self._spatial, "depth": self._depth,
                  "fine": self._fine, "refine": self._refine, "levels": self._levels,
                  "final_drr": self._final_drr}.get(name)
        if runner is None:
            raise ValueError(f"unknown stage {name!r}; stages are {', '.join(STAGES)}")
        self._report(name, 0.0, f"{name} started")
        drop_results_from(state, name)
        start = time.perf_counter()
        extra = runner(state) or {}
        if state.pyramid.cache is not None:
            state.warnings += state.pyramid.cache.take_notes()
        pose = state.pose
        m = float(mpde_mm(state.geometry, pose, state.pairs.points_lps_mm, state.pairs.uv_px)) \
            if name in ("spatial", "depth", "fine", "refine") and state.pairs is not None else None
        stage = StageResult(name, CarmPose.from_array(pose), m, time.perf_counter() - start, extra)
        state.stages.append(stage)
        self._report(name, 1.0, f"{name} done" + (f": mPDE {m:.2f} mm" if m is not None else ""))
        return stage

    def _coarse_grid(self, state: RegistrationState) -> tuple[np.ndarray, np.ndarray]:
        p = state.parameters
        ty = grid(p.ty_half_range_mm, p.grid_step_mm)
        if p.tz_half_range_mm is not None:
            return ty, grid(p.tz_half_range_mm, p.grid_step_mm)
        iso_z = state.geometry.isocenter_lps_mm[2]
        z = state.ct_landmarks.points_lps_mm[:, 2] - iso_z
        lo, hi = np.floor((z.min() - 20.0) / p.grid_step_mm), np.ceil((z.max() + 20.0) / p.grid_step_mm)
        return ty, p.grid_step_mm * np.arange(min(lo, -1), max(hi, 1) + 1)

    def _database(self, state: RegistrationState) -> dict:
        p = state.parameters
        intr = state.geometry.intrinsics.binned(state.coarse_factor)
        ty, tz = self._coarse_grid(state)
        digest = state.pyramid.digest(p.coarse_spacing_mm)
        state.database = build_database(lambda: state.pyramid.level(p.coarse_spacing_mm), state.geometry, intr,
                                        ty, tz, 0.0, p.cache_dir, digest=digest,
                                        progress=lambda f: self._report("database", min(f, 0.999), "rendering DRRs"))
        state.warnings += state.database.notes
        return {"drrs": int(len(ty) * len(tz)), "from_cache": state.database.from_cache,
                "detector_px": list(intr.size_px), "key": state.database.key}

    def _spatial(self, state: RegistrationState) -> dict:
        appearance = self._appearance.decide(state)
        shape = state.database.drrs.shape[2:]
        xc = bin_image_to(state.xray_line_integral, state.coarse_factor, shape)
        mc = bin_mask_to(state.mask, state.coarse_factor, shape)
        p = state.parameters
        state.spatial = spatial_search(state.database, xc, mc, p.metric,
                                       METRICS if p.all_metrics else (p.metric,),
                                       known=None if state.known_gc is None else {"gc": state.known_gc})
        per_metric = {}
        for name, (ty, tz) in state.spatial.best_by_metric.items():
            pose = np.array([state.database.tx_mm, ty, tz, 0, 0, 0])
            per_metric[name] = {"ty_mm": ty, "tz_mm": tz, "mpde_mm": None if state.pairs is None else float(
                mpde_mm(state.geometry, pose, state.pairs.points_lps_mm, state.pairs.uv_px))}
        return {"metric": p.metric, "per_metric": per_metric,
                "seconds_by_metric": dict(state.spatial.seconds_by_metric),
                "polarity": appearance["polarity"]}  # the whole decision: result.json "appearance"

    def _depth(self, state: RegistrationState) -> dict:
        p = state.parameters
        if state.pairs is None:
            return {"skipped": "no clicks: the pose comes from the image alone (levels stage)"}
        fit = chosen_fit(state)
        if fit is not None:  # the levels stage ran this very search for the chosen labelling
            state.depth = fit.depth
        else:
            state.depth = depth_search(state.geometry, state.spatial.ty_mm, state.spatial.tz_mm,
                                       state.pairs.points_lps_mm, state.pairs.uv_px, p.depth_far_mm, p.depth_step_mm,
                                       magnification_range=p.magnification_range)
        return {"tx_mm": state.depth.tx_mm, "ty_mm": state.depth.ty_mm, "tz_mm": state.depth.tz_mm,
                "magnification": state.depth.magnification,
                "intervertebral_cost_mm": state.depth.cost_mm, "from_levels_stage": fit is not None}

    def _fine(self, state: RegistrationState) -> dict:
        if state.pairs is None:
            return {"skipped": "no clicks"}
        fit = chosen_fit(state)
        if fit is not None and state.depth is fit.depth:  # the levels stage's fine search from the same start
            state.fine = fit.fine
        else:
            state.fine = fine_search(state.geometry, state.pose, state.pairs.points_lps_mm, state.pairs.uv_px,
                                     state.parameters.fine, should_stop=self._check_cancel)
        return {"evaluations": state.fine.evaluations, "objective": state.fine.objective,
                "from_levels_stage": fit is not None and state.fine is fit.fine}

    def _levels(self, state: RegistrationState) -> dict:
        p = state.parameters
        clicks = state.xray_landmarks
        state.pairs = state.given_pairs
        if clicks.named and len(clicks.labels) and not p.level_check:
            return {"enabled": False}
        if len(clicks.labels) == 0:
            ctx = self._levels_context(state)
            checked = state.image_polarity
            if checked is not None and checked.without_shading_mm > 0:  # the second opinion's polarity: its way
                ctx = unshaded_context(ctx, checked.without_shading_mm)
            reuse = checked.pairs(state.appearance.polarity) if checked else ()
            ident = identify_from_image(ctx, state.ct_landmarks, self._image_starts(state), p.identify,
                                        state.appearance is None or state.appearance.trusted, registered=reuse)
        else:
            ident = self._levels_at_clicks(state)
            chosen = ident.chosen
            uv = np.asarray(clicks.uv_px, float)[ident.click_indices][ident.order]
            ct = state.ct_landmarks.as_dict()
            state.pairs = Pairs(list(chosen.labels), np.array([ct[lb] for lb in chosen.labels]), uv, [])
        state.identification = ident
        if ident.status == "ambiguous":
            state.warnings.append(ident.message)
        # the answer itself is the result's level_check (result.json "level_check"), not repeated here
        return {"enabled": True, "status": ident.status, "labellings_registered": sum(f.refined for f in ident.fits),
                "refinements": state.refinements.as_dict()}

    def _levels_context(self, state: RegistrationState) -> FitContext:
        """Where the levels stage registers: the X-ray's attenuation image as converted by the appearance in use, its
        equalised image for ``agreement``, from the spatial stage's offsets, with the stage's progress hook."""
        clicks, p = state.xray_landmarks, state.parameters
        ctx = state_context(state, state.xray_line_integral, state.spatial.ty_mm, state.spatial.tz_mm,
                            self._check_cancel, self._labelling_progress(len(clicks.labels), clicks.named,
                                                                         len(ct_level_names(state.ct_landmarks)),
                                                                         p.identify))
        bone_dark = state.appearance.bone_dark if state.appearance is not None else state.xray.bone_dark
        ctx.xray_equalised = attenuation(state.xray.pixels, state.mask, bone_dark, EQUALISED)  # ``agreement``
        return ctx

    def _levels_at_clicks(self, state: RegistrationState) -> LevelIdentification:
        """The levels contest at the clicks (``_open_contest_at_clicks``, ``_finish_contest``), and the contest under
        the other polarity when it is worth running (``AppearanceChecks.worth_other_polarity``,
        ``contest_under_other_polarity``), asked first of the contest's leader before its searches for confidence:
        when the leader already explains the image poorly under an unclear polarity, the other polarity's contest
        runs then, and the first contest is searched and decided only when that one is not taken (since stop 50:
        report case 271's flat-panel DICOM spent 29 of its 51 s searching under the polarity the second contest then
        overturned). Otherwise the same is asked of the first contest's winner once it is decided. The second
        contest's answer is the same either way (it starts afresh); only a first contest whose searches would have
        lifted its leader to one that explains the image can now meet a second contest it did not before."""
        opened = self._open_contest_at_clicks(state)
        asked_before = self._appearance.worth_other_polarity(state, opened.leader)
        if asked_before:
            again = self._appearance.contest_under_other_polarity(state, opened.leader, None, opened.plan.fits,
                                                                  lambda: self._contest_at_clicks(state))
            if again is not None:
                return again
        ident = self._finish_contest(state, opened)
        if not asked_before and self._appearance.worth_other_polarity(state, ident.winner):
            again = self._appearance.contest_under_other_polarity(state, ident.winner, ident.status, ident.fits,
                                                                  lambda: self._contest_at_clicks(state))
            return ident if again is None else again
        return ident

    def _contest_at_clicks(self, state: RegistrationState) -> LevelIdentification:
        """The contest between the clicks' labellings on the X-ray as converted by the appearance in use, opened and
        finished at once."""
        return self._finish_contest(state, self._open_contest_at_clicks(state))

    def _open_contest_at_clicks(self, state: RegistrationState) -> OpenContest:
        """The clicks' labellings registered and settled (``open_contest``) on the X-ray as converted by the
        appearance in use, reusing the polarity check's registrations under it."""
        return open_contest(self._levels_context(state), state.ct_landmarks, state.xray_landmarks,
                            state.parameters.identify, registered=self._registered_at_clicks(state))

    def _finish_contest(self, state: RegistrationState, opened: OpenContest) -> LevelIdentification:
        """The contest decided (``finish_contest``), its winner judged by the appearance checks
        (``AppearanceChecks.with_winner``); without the searches that serve only a confident verdict when the
        appearance stays untrusted whatever labelling wins (``AppearanceChecks.trust_within_reach``)."""
        a = state.appearance

        def judge(winner):  # the appearance judged again with the contest's winner (none to judge: no call)
            return self._appearance.with_winner(state, winner)

        return finish_contest(opened, a is None or a.trusted, judge_appearance=None if a is None else judge,
                              confidence_possible=self._appearance.trust_within_reach(state, opened.plan.fits))

    @staticmethod
    def _image_starts(state: RegistrationState) -> list:
        """No clicks: where the search on the image alone starts (``image_starts``) on the X-ray as converted: the
        polarity check's own starts when it judged the polarity in use (the same image, so its refinements are
        reused), else computed here (a polarity the user set)."""
        checked, p, db = state.image_polarity, state.parameters, state.database
        if checked is not None and state.appearance.polarity in checked.starts:
            return list(checked.starts[state.appearance.polarity])
        rows, cols = db.drrs.shape[2:]
        return image_starts(db, bin_image_to(state.xray_line_integral, state.coarse_factor, (rows, cols)),
                            bin_mask_to(state.mask, state.coarse_factor, (rows, cols)), p.identify.image_starts)

    @staticmethod
    def _registered_at_clicks(state: RegistrationState) -> list:
        """The polarity check's registrations under the polarity and storage in use (``click_polarity``)."""
        cp, a = state.click_polarity, state.appearance
        if cp is None or a is None or a.polarity not in cp.registered:
            return []
        same_image = a.polarity == "bone-bright" or a.storage == cp.dark_storage
        return list(cp.registered[a.polarity]) if same_image else []

    def _labelling_progress(self, n_clicks: int, named: bool, n_ct_levels: int, p: IdentifyParameters):
        """The levels stage's progress hook (``FitContext.on_labelling``): "labelling 3 of 7: T10, T11, T12"
        before each registration of a labelling. 7 = the usual count: the first candidates and the winner's two
        neighbours (unnamed; at most the runs of consecutive CT levels), the given names and one level up and
        down (named), the map's peaks and one challenge (no clicks), plus the leading two refitted from each
        other's pose (``confirm_leaders``); raised when more are needed."""
        runs = max(n_ct_levels - n_clicks + 1, 1)
        expected = p.image_starts + 2 if n_clicks == 0 else min(3 if named else p.candidates + 2, runs)
        if n_clicks and p.confirm_leaders:
            expected += min(2, runs - 1)
        count = {"done": 0, "expected": expected}

        def on_labelling(labels: list) -> None:
            count["done"] += 1
            count["expected"] = max(count["expected"], count["done"])
            done, total = count["done"], count["expected"]
            what = ", ".join(labels) if labels else "a pose from the image"
            self._report("levels", min((done - 1) / total, 0.99), f"labelling {done} of {total}: {what}")
        return on_labelling

    def _refine(self, state: RegistrationState) -> dict:
        p = state.parameters
        if not p.refine.enabled:
            return {"enabled": False}
        coarse_pose, reused, extra = self._coarse_refined_pose(state, *_pair_arrays(state.pairs))
        estimate = None
        if pincushion_unknown(state):
            def progress(done: int, total: int) -> None:
                self._report("refine", 0.5 + 0.4 * done / total,
                             f"estimating the image intensifier's pincushion ({done + 1} of up to {total})")

            estimate = estimate_pincushion(lambda shift: self._local_refine(state, coarse_pose, shift),
                                           grid_for(state.geometry.intrinsics.max_distortion_mm), progress,
                                           acceptable=lambda refined: self._accepted(state, refined))
            r = estimate.refine
        else:
            self._report("refine", 0.5, "local image refinement")
            r = self._local_refine(state, coarse_pose)
        state.refine = r
        accepted = self._accepted(state, r)
        if estimate is not None:
            extra["pincushion"] = {**estimate.as_dict(), "taken": accepted}
        if accepted:
            state.refined_pose = r.pose
            if estimate is not None:  # the pose found with it: the detector has it from now on
                take_pincushion(state, estimate)
        else:  # the landmark pose, found on the detector as prepared, is kept with it
            state.warnings.append(f"the image refinement moved the clicked levels {r.mpde_mm:.1f} mm from the "
                                  "clicks; kept the landmark pose (check the clicks and the level names)")
        return {"enabled": True, "accepted": accepted, "coarse_reused_from_levels": reused,
                "evaluations": r.evaluations, "similarity_start": r.similarity_start,
                "similarity_end": r.similarity_end, "refined_mpde_mm": r.mpde_mm, **extra}

    @staticmethod
    def _accepted(state: RegistrationState, refined) -> bool:
        """Whether a refinement's pose may be kept: the clicks still within ``refine_max_mpde_mm`` of it."""
        return state.pairs is None or refined.mpde_mm <= state.parameters.refine_max_mpde_mm

    def _local_refine(self, state: RegistrationState, start_pose: np.ndarray, shift_mm: float | None = None):
        """The local image refinement (``intensity_refine``, ``parameters.refine``) from ``start_pose``; with
        ``shift_mm``, on the detector given that pincushion (``pincushion.with_shift``), the clicks taken to their
        ideal points through it."""
        p = state.parameters
        geometry, pairs = state.geometry, state.pairs
        if shift_mm is not None:  # the pairs' clicks are as shown (``pincushion_unknown``: no distortion given)
            geometry = with_shift(state.geometry, shift_mm)
            pairs = None if pairs is None else ideal_clicks(pairs, geometry.intrinsics)
        points, uv = _pair_arrays(pairs)
        return intensity_refine(state.pyramid.level(p.refine.mu_spacing_mm), geometry, start_pose,
                                state.xray_line_integral, state.mask, points, uv, p.refine,
                                should_stop=self._check_cancel)

    def _coarse_refined_pose(self, state: RegistrationState, points: np.ndarray, uv: np.ndarray
                             ) -> tuple[np.ndarray, bool, dict]:
        """The wide coarse pass: taken from the levels stage when it fully refined the chosen labelling from the
        same landmark pose (the identical computation), else run here; then, with clicks, refined once more from the
        clicks' fit at the nominal depth (``labelling_fit.refit_at_nominal_depth``), the better kept. Returns (pose,
        reused from the levels stage, what the nominal-depth start did for result.json)."""
        ident = state.identification
        if ident is not None and ident.mode == "image_only":
            return np.asarray(ident.winner.pose, float), True, {}
        fit = chosen_fit(state)
        reused = fit is not None and fit.refined and state.fine is fit.fine
        ctx = state_context(state, state.xray_line_integral, state.spatial.ty_mm, state.spatial.tz_mm,
                            self._check_cancel)
        if not reused:
            labels = list(state.pairs.labels) if state.pairs is not None else []
            fit = refit_from(ctx, LabellingFit(labels, 0, points, uv, state.depth, state.fine), state.pose)
        if len(points) == 0 or not state.parameters.nominal_depth_start:
            return fit.pose, reused, {}
        other = refit_at_nominal_depth(ctx, fit.copy())
        taken = other.refine is not fit.refine
        return other.pose, reused, {"nominal_depth_start": {
            "taken": taken, "objective": other.runs[-1], "objective_before": fit.score,
            "stopped_back_at_evaluations": other.rejoined[-1] if len(other.rejoined) > len(fit.rejoined) else None}}

    def _final_drr(self, state: RegistrationState) -> dict:
        p, intr = state.parameters, state.geometry.intrinsics
        cols, rows = intr.size_px
        target = final_drr_detector(intr, state.geometry.sod_mm, float(np.min(state.pyramid.volume.spacing_mm)),
                                    p.final_drr_max_px, p.final_drr_rays_per_voxel)
        drr = render_line_integrals(state.pyramid.level(None), state.geometry, state.pose, target)
        if target is not intr:
            from scipy import ndimage
            drr = ndimage.zoom(drr, (rows / drr.shape[0], cols / drr.shape[1]), order=1)
        state.drr_line_integral = drr.astype(np.float32)
        return {"detector_px": list(target.size_px)}

    # ------------------------------------------------------------------ result
    def save_result(self, result: RegistrationResult, out_dir, xray_pixels: np.ndarray | None = None,
                    clicked: dict | None = None, ct=None, ct_landmarks=None) -> dict:
        """Write result.json, overlay.png, drr.png/.nrrd, carm.tfm and figures (``report.save_result``); given
        the CT and its landmarks, the 3D Slicer scene too."""
        from carmreg.logic.report.result_files import save_result

        pixels = xray_pixels if xray_pixels is not None else result.xray_line_integral
        return save_result(result, out_dir, pixels, clicked, ct=ct, ct_landmarks=ct_landmarks)

    # ------------------------------------------------------------------ result
    def result(self, state: RegistrationState) -> RegistrationResult:
        return build_result(state)
