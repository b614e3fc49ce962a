"""The logic class: the three-stage registration, orchestrated (method paper 3.1.6 and 3.2).

``CarmRegLogic`` is what the CLI, the GUI and the headless tests drive. It takes explicit arguments, raises
``CarmRegError`` on bad input, reports progress through ``progress(stage, fraction, message)`` and honours
``cancel()`` between steps (``CancelledError``).

Stages (each a plain function in its own module, returning a small result):
  database  - DRRs of the 4 mm mu level over a (ty, tz) grid at tx = 0 (``database``, Algorithm 1), cached;
  spatial   - similarity of the coarse X-ray with every DRR -> (ty, tz) (``spatial_search``, Algorithm 2);
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
              same computation for the chosen labelling) then a local one (3 mm); it fixes the out-of-plane
              rotations and the magnification that three nearly collinear clicks cannot; its pose is kept only
              if the clicks still agree with it;
  final_drr - DRR of the full-resolution CT at the final pose on the X-ray's detector.

Geometry: the nominal AP C-arm has its isocentre at the CT volume centre (paper 3.1.3) and its source at
``sod_mm`` from it (the X-ray's DICOM DistanceSourceToPatient when known, else 0.6 x SDD: ``camera.nominal_geometry``).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.drr.cpu import render_line_integrals
from carmreg.logic.errors import CancelledError, LandmarkError, RegistrationError
from carmreg.logic.geometry.camera import CarmGeometry, CarmPose, nominal_geometry, project
from carmreg.logic.geometry.projection_distance import mpde_mm, pde_mm
from carmreg.logic.geometry.volume import MuPyramid, Volume
from carmreg.logic.image.appearance import (
    CLEAR_POLARITY_GC,
    POLARITIES,
    Appearance,
    decide_polarity,
    fixed_appearance,
    image_polarity,
    orientation_scores,
    polarity_scores,
    storage_gc,
)
from carmreg.logic.image.field import field_mask
from carmreg.logic.image.prepare import attenuation, bin_image, bin_mask, coarse_factor
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D, Pairs, level_index, pair_by_label, spine_order_warnings
from carmreg.logic.io.xray import XrayImage
from carmreg.logic.registration.database import DrrDatabase, build_database, grid, source_digest
from carmreg.logic.registration.depth import DepthResult, depth_search, tx_limits
from carmreg.logic.registration.fine import FineParameters, FineResult, fine_search
from carmreg.logic.registration.image_refine import RefineParameters, RefineResult, intensity_refine
from carmreg.logic.registration.labelling_fit import FitContext, LabellingFit, coarse_refine_parameters
from carmreg.logic.registration.labellings import check_labelling_possible, ct_level_names, identifiable_clicks
from carmreg.logic.registration.levels import (
    IdentifyParameters,
    LevelIdentification,
    identify_from_image,
    identify_levels,
)
from carmreg.logic.registration.sanity import check_ct_content, check_xray_content
from carmreg.logic.registration.spatial import SpatialResult, spatial_search
from carmreg.logic.similarity.metrics import METRICS

STAGES = ("database", "spatial", "levels", "depth", "fine", "refine", "final_drr")
MIN_CLICKS = 3  # X-ray clicks needed (named or not); zero clicks = levels from the image alone


@dataclass
class RegistrationParameters:
    """Every choice of the pipeline, with the paper's value where it gives one."""

    metric: str = "gc"                      # spatial-search metric (paper: PSNR); see README for why GC
    polarity: str = "auto"                  # auto (found from the image) | bone-dark | bone-bright
    all_metrics: bool = False               # also compute the other six maps (paper Fig. 6; ~7x the time)
    coarse_spacing_mm: float = 4.0          # mu level and coarse detector pixel (paper: 4 mm)
    ty_half_range_mm: float = 50.0          # medio-lateral search +- (paper: 50)
    tz_half_range_mm: float | None = None   # superior-inferior +-; None = cover every labelled CT level
    grid_step_mm: float = 2.0               # database step (paper: 2 mm)
    depth_far_mm: float = 400.0             # farthest source retreat (paper: 40-50 cm)
    depth_step_mm: float = 10.0             # paper: 10 mm
    fine: FineParameters = field(default_factory=FineParameters)
    refine_coarse: RefineParameters = field(default_factory=coarse_refine_parameters)
    refine: RefineParameters = field(default_factory=RefineParameters)
    refine_max_mpde_mm: float = 4.0         # refined pose rejected when the clicks disagree more than this
    level_check: bool = True                # named clicks: also try the names shifted +-1, +-2 levels
    identify: IdentifyParameters = field(default_factory=IdentifyParameters)
    final_drr_max_px: int = 1024            # final DRR detector size cap (longest side)
    max_fine_mpde_mm: float = 6.0           # fine-stage mPDE above this = failed check (clicks are ~1-3 mm)
    magnification_range: tuple = (1.05, 3.0)
    cache_dir: str | None = None

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class StageResult:
    name: str
    pose: CarmPose
    mpde_mm: float | None
    seconds: float
    extra: dict = field(default_factory=dict)


@dataclass
class RegistrationState:
    """Everything the stages share; filled stage by stage."""

    ct: Volume
    ct_landmarks: Landmarks3D
    xray: XrayImage
    xray_landmarks: Landmarks2D
    parameters: RegistrationParameters
    geometry: CarmGeometry
    pairs: Pairs | None                     # None until the levels stage names unnamed clicks (or no clicks)
    pyramid: MuPyramid
    xray_line_integral: np.ndarray
    mask: np.ndarray
    coarse_factor: int
    database: DrrDatabase | None = None
    spatial: SpatialResult | None = None
    depth: DepthResult | None = None
    fine: FineResult | None = None
    refine: RefineResult | None = None
    refined_pose: np.ndarray | None = None
    identification: LevelIdentification | None = None
    appearance: Appearance | None = None    # polarity and storage: the header's until the spatial stage decides
    known_gc: np.ndarray | None = None      # GC of the chosen bone-dark conversion with every DRR (spatial stage)
    given_pairs: Pairs | None = None        # the clicks as named by the surgeon (all named), else None
    drr_line_integral: np.ndarray | None = None
    stages: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    @property
    def pose(self) -> np.ndarray:
        """The best pose so far (6,)."""
        if self.refined_pose is not None:
            return self.refined_pose
        if self.fine is not None:
            return self.fine.pose
        if self.depth is not None:
            return np.array([self.depth.tx_mm, self.depth.ty_mm, self.depth.tz_mm, 0, 0, 0], float)
        if self.identification is not None and self.identification.mode == "image_only":
            return np.asarray(self.identification.winner.pose, float)
        if self.spatial is not None:
            return np.array([self.database.tx_mm, self.spatial.ty_mm, self.spatial.tz_mm, 0, 0, 0], float)
        return np.zeros(6)


@dataclass
class RegistrationResult:
    pose: CarmPose
    projection_matrix: np.ndarray
    geometry: CarmGeometry
    stages: list
    levels: list                    # [{"label", "uv_px", "fitted", "pde_mm", "in_image", "clicked_uv_px",
    #                                  "name_margin"}] for every CT-labelled level
    drr_line_integral: np.ndarray | None
    xray_line_integral: np.ndarray
    convergence: list
    trajectory: list
    similarity_maps: dict
    database_grid: dict
    ok: bool
    warnings: list
    parameters: RegistrationParameters
    inputs: dict = field(default_factory=dict)
    level_check: dict | None = None  # LevelIdentification.as_dict(): mode, status, margin, assigned_labels ...
    appearance: Appearance | None = None  # the X-ray's polarity and storage, and the evidence
    field_mask: np.ndarray | None = None  # (rows, cols) exposed field of the X-ray

    @property
    def magnification(self) -> float:
        return float(self.geometry.magnification(self.pose))


class CarmRegLogic:
    """Headless logic class: ``register(...)`` or ``prepare(...)`` then ``run_stage(state, name)``."""

    def __init__(self, progress=None):
        self.progress = progress
        self._cancel = False

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
        pairs, notes = _given_pairs(ct_landmarks, xray_landmarks)
        _check_landmarks(ct, ct_landmarks, xray, xray_landmarks)
        geometry = nominal_geometry(intrinsics, ct, xray.sod_mm)
        if params.polarity not in ("auto", *POLARITIES):
            raise RegistrationError(f"polarity {params.polarity!r}: use auto, {' or '.join(POLARITIES)}")
        mask = field_mask(xray.pixels)
        appearance = _initial_appearance(xray, params)
        line_integral = attenuation(xray.pixels, mask, appearance.bone_dark, appearance.storage)
        factor = coarse_factor(intrinsics.pixel_spacing_mm, params.coarse_spacing_mm)
        return RegistrationState(ct, ct_landmarks, xray, xray_landmarks, params, geometry, pairs,
                                 MuPyramid(ct), line_integral, mask, factor, given_pairs=pairs, warnings=notes,
                                 appearance=appearance)

    def register(self, ct: Volume, ct_landmarks: Landmarks3D, xray: XrayImage, xray_landmarks: Landmarks2D,
                 parameters: RegistrationParameters | None = None) -> RegistrationResult:
        """Run every stage and return the result (``ok`` False, with reasons, when a check fails)."""
        state = self.prepare(ct, ct_landmarks, xray, xray_landmarks, parameters)
        for name in STAGES:
            self.run_stage(state, name)
        return self.result(state)

    # ------------------------------------------------------------------ stages
    def run_stage(self, state: RegistrationState, name: str) -> StageResult:
        runner = {"database": self._database, "spatial": self._spatial, "depth": self._depth,
                  "fine": self._fine, "refine": self._refine, "levels": self._levels,
                  "final_drr": self._final_drr}.get(name)
        if runner is None:
            raise ValueError(f"unknown stage {name!r}; stages are {', '.join(STAGES)}")
        self._report(name, 0.0, f"{name} started")
        _drop_results_from(state, name)
        start = time.perf_counter()
        extra = runner(state) or {}
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
        digest = source_digest(state.ct.hu, state.ct.ijk_to_lps, p.coarse_spacing_mm, state.pyramid.mu_water_per_mm)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            state.database = build_database(lambda: state.pyramid.level(p.coarse_spacing_mm), state.geometry, intr,
                                            ty, tz, 0.0, p.cache_dir, digest=digest,
                                            progress=lambda f: self._report("database", min(f, 0.999),
                                                                            "rendering DRRs"))
        state.warnings += [str(w.message) for w in caught]
        return {"drrs": int(len(ty) * len(tz)), "from_cache": state.database.from_cache,
                "detector_px": list(intr.size_px), "key": state.database.key}

    def _decide_appearance(self, state: RegistrationState) -> dict:
        """Polarity and storage from the image against the database (``image.appearance``); the X-ray's
        attenuation image is rebuilt with them."""
        p, xray = state.parameters, state.xray
        rows, cols = state.database.drrs.shape[2:]
        drrs = state.database.drrs.reshape(-1, rows, cols)
        scores = polarity_scores(xray.pixels, state.mask, drrs, state.coarse_factor)
        refined = None
        if p.polarity == "auto" and image_polarity(scores)[1] < CLEAR_POLARITY_GC:
            self._report("spatial", 0.3, "telling bone-dark from bone-bright")
            refined = self._refined_polarity_scores(state, scores)
        state.appearance = a = decide_polarity(scores, refined, p.polarity, xray.bone_dark,
                                               xray.sources.get("bone_dark", ""))
        state.known_gc = None
        if a.bone_dark:  # a bone-bright image is attenuation-like already: no storage to choose
            gc_by_storage = storage_gc(xray.pixels, state.mask, drrs, state.coarse_factor)
            a.set_storage(gc_by_storage)
            state.known_gc = gc_by_storage[a.storage]  # the spatial stage's GC map, computed here already
        a.set_orientation(orientation_scores(xray.pixels, state.mask, state.database.drrs, state.coarse_factor,
                                             a.bone_dark))
        state.xray_line_integral = attenuation(xray.pixels, state.mask, a.bone_dark, a.storage)
        if not a.clear:
            state.warnings.append(f"X-ray polarity: {a.note}")
        if a.orientation == "as-stored" and not a.orientation_clear:
            state.warnings.append("X-ray orientation: the image matches the CT mirrored or turned almost as well as "
                                  "as stored; check that the display is not mirrored or rotated")
        return a.as_dict()

    def _refined_polarity_scores(self, state: RegistrationState, scores: dict) -> dict:
        """The tie-break of an unclear polarity: each polarity's best database pose refined on the image alone
        (the levels stage's coarse refinement, no clicks); its final GC is that polarity's score."""
        p, db = state.parameters, state.database
        level = state.pyramid.level(p.refine_coarse.mu_spacing_mm)
        nz = len(db.tz_mm)
        out = {}
        for polarity in POLARITIES:
            iy, iz = divmod(scores["best_index"][polarity], nz)
            start = np.array([db.tx_mm, db.ty_mm[iy], db.tz_mm[iz], 0.0, 0.0, 0.0])
            line = attenuation(state.xray.pixels, state.mask, polarity == "bone-dark")
            r = intensity_refine(level, state.geometry, start, line, state.mask, np.zeros((0, 3)), np.zeros((0, 2)),
                                 p.refine_coarse, should_stop=self._check_cancel)
            out[polarity] = float(r.similarity_end)
        return out

    def _spatial(self, state: RegistrationState) -> dict:
        appearance = self._decide_appearance(state)
        xc = bin_image(state.xray_line_integral, state.coarse_factor)
        mc = bin_mask(state.mask, state.coarse_factor)
        rows, cols = state.database.drrs.shape[2:]
        p = state.parameters
        state.spatial = spatial_search(state.database, xc[:rows, :cols], mc[:rows, :cols], p.metric,
                                       METRICS if p.all_metrics else (p.metric,),
                                       known=None if state.known_gc is None else {"gc": state.known_gc})
        per_metric = {}
        for name, (ty, tz) in state.spatial.best_by_metric.items():
            pose = np.array([state.database.tx_mm, ty, tz, 0, 0, 0])
            per_metric[name] = {"ty_mm": ty, "tz_mm": tz, "mpde_mm": None if state.pairs is None else float(
                mpde_mm(state.geometry, pose, state.pairs.points_lps_mm, state.pairs.uv_px))}
        return {"metric": p.metric, "per_metric": per_metric,
                "seconds_by_metric": dict(state.spatial.seconds_by_metric), "appearance": appearance}

    def _depth(self, state: RegistrationState) -> dict:
        p = state.parameters
        if state.pairs is None:
            return {"skipped": "no clicks: the pose comes from the image alone (levels stage)"}
        fit = _chosen_fit(state)
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
        fit = _chosen_fit(state)
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
        ctx = FitContext(state.pyramid.level(p.refine_coarse.mu_spacing_mm), state.geometry,
                         state.xray_line_integral, state.mask, state.spatial.ty_mm, state.spatial.tz_mm,
                         p.fine, p.refine_coarse, p.magnification_range, p.depth_far_mm, p.depth_step_mm,
                         self._check_cancel,
                         self._labelling_progress(len(clicks.labels), clicks.named,
                                                  len(ct_level_names(state.ct_landmarks)), p.identify))
        appearance_clear = state.appearance is None or state.appearance.trusted
        if len(clicks.labels) == 0:
            ident = identify_from_image(ctx, state.ct_landmarks, state.spatial.maps[p.metric],
                                        state.database.ty_mm, state.database.tz_mm, state.database.tx_mm,
                                        p.identify, appearance_clear)
        else:
            ident = identify_levels(ctx, state.ct_landmarks, clicks, p.identify, appearance_clear)
            chosen = ident.chosen
            uv = np.asarray(clicks.uv_px, float)[ident.click_indices][ident.order]
            ct = state.ct_landmarks.as_dict()
            state.pairs = Pairs(list(chosen.labels), np.array([ct[lb] for lb in chosen.labels]), uv, [])
        state.identification = ident
        if ident.status == "ambiguous":
            state.warnings.append(ident.message)
        return {"enabled": True, **ident.as_dict()}

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
        points, uv = (state.pairs.points_lps_mm, state.pairs.uv_px) if state.pairs is not None \
            else (np.zeros((0, 3)), np.zeros((0, 2)))
        coarse_pose, reused = self._coarse_refined_pose(state, points, uv)
        self._report("refine", 0.5, "local image refinement")
        r = intensity_refine(state.pyramid.level(p.refine.mu_spacing_mm), state.geometry, coarse_pose,
                             state.xray_line_integral, state.mask, points, uv, p.refine, should_stop=self._check_cancel)
        state.refine = r
        accepted = state.pairs is None or r.mpde_mm <= p.refine_max_mpde_mm
        if accepted:
            state.refined_pose = r.pose
        else:
            state.warnings.append(f"the image refinement moved the clicked levels {r.mpde_mm:.1f} mm from the "
                                  "clicks; kept the landmark pose (check the clicks and the level names)")
        return {"enabled": True, "accepted": accepted, "coarse_reused_from_levels": reused,
                "evaluations": r.evaluations, "similarity_start": r.similarity_start,
                "similarity_end": r.similarity_end, "refined_mpde_mm": r.mpde_mm}

    def _coarse_refined_pose(self, state: RegistrationState, points: np.ndarray, uv: np.ndarray
                             ) -> tuple[np.ndarray, bool]:
        """The wide coarse pass: taken from the levels stage when it fully refined the chosen labelling from the
        same landmark pose (the identical computation), else run here."""
        ident = state.identification
        if ident is not None and ident.mode == "image_only":
            return np.asarray(ident.winner.pose, float), True
        fit = _chosen_fit(state)
        if fit is not None and fit.refined and state.fine is fit.fine:
            return fit.pose, True
        p = state.parameters
        r = intensity_refine(state.pyramid.level(p.refine_coarse.mu_spacing_mm), state.geometry, state.pose,
                             state.xray_line_integral, state.mask, points, uv, p.refine_coarse,
                             should_stop=self._check_cancel)
        return r.pose, False

    def _final_drr(self, state: RegistrationState) -> dict:
        intr = state.geometry.intrinsics
        cols, rows = intr.size_px
        scale = min(1.0, state.parameters.final_drr_max_px / max(cols, rows))
        target = intr if scale >= 1.0 else intr.scaled_to((int(round(cols * scale)), int(round(rows * scale))))
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

    def result(self, state: RegistrationState) -> RegistrationResult:
        pose = CarmPose.from_array(state.pose)
        P = state.geometry.projection_matrix(pose)
        fitted = set(state.pairs.labels) if state.pairs is not None else set()
        clicked = dict(zip(state.pairs.labels, state.pairs.uv_px, strict=True)) if state.pairs is not None else {}
        spacing = state.geometry.intrinsics.pixel_spacing_mm
        named = _name_margins(state.identification)
        levels = []
        for label, point in sorted(state.ct_landmarks.as_dict().items(), key=lambda kv: level_index(kv[0])):
            uv = project(P, point[None])[0]
            pde = float(pde_mm(P, point[None], clicked[label][None], spacing)[0]) if label in clicked else None
            levels.append({"label": label, "uv_px": [float(uv[0]), float(uv[1])], "fitted": label in fitted,
                           "pde_mm": pde, "in_image": _in_image(uv, state.geometry.intrinsics.size_px),
                           "clicked_uv_px": [float(x) for x in clicked[label]] if label in clicked else None,
                           "name_margin": named.get(label)})
        problems = self._checks(state, pose)
        spatial = state.spatial
        return RegistrationResult(
            pose=pose, projection_matrix=P, geometry=state.geometry, stages=list(state.stages), levels=levels,
            drr_line_integral=state.drr_line_integral, xray_line_integral=state.xray_line_integral,
            convergence=state.fine.convergence if state.fine else [],
            trajectory=state.fine.trajectory if state.fine else [],
            similarity_maps=spatial.maps if spatial else {},
            database_grid={"ty_mm": state.database.ty_mm.tolist(), "tz_mm": state.database.tz_mm.tolist()}
            if state.database else {},
            ok=not problems, warnings=state.warnings + problems, parameters=state.parameters,
            level_check=state.identification.as_dict() if state.identification else None,
            appearance=state.appearance, field_mask=state.mask,
            inputs={"ct": state.ct.source, "xray": state.xray.source, "ct_landmarks": state.ct_landmarks.source,
                    "xray_landmarks": state.xray_landmarks.source, "geometry_sources": dict(state.xray.sources),
                    "xray_frame": state.xray.meta.get("frame"),
                    "xray_frames_in_file": state.xray.meta.get("n_frames")})

    def _checks(self, state: RegistrationState, pose: CarmPose) -> list[str]:
        """The pipeline's own sanity checks; any message here makes ``ok`` False."""
        problems = []
        p = state.parameters
        image_only = state.identification is not None and state.identification.mode == "image_only"
        if state.fine is None and not image_only:
            problems.append("the fine stage did not run")
        elif state.fine is not None and state.fine.mpde_mm > p.max_fine_mpde_mm:
            problems.append(f"fine-stage mPDE {state.fine.mpde_mm:.1f} mm exceeds {p.max_fine_mpde_mm:.1f} mm: "
                            "the landmarks do not agree with any rigid C-arm pose; check the level names")
        mag = float(state.geometry.magnification(pose))
        lo, hi = p.magnification_range
        if not lo <= mag <= hi:
            problems.append(f"magnification {mag:.2f} is outside the C-arm range {lo}-{hi}; check SDD, pixel "
                            "spacing and the landmarks")
        if state.ct.contains_lps(state.geometry.source_lps_mm(pose)[None], margin_vox=0.0)[0]:
            problems.append("the found X-ray source lies inside the CT volume: degenerate pose")
        a = state.appearance
        if a is not None and a.orientation != "as-stored":
            best, stored = a.orientation_scores[a.orientation], a.orientation_scores["as-stored"]
            problems.append(f"the X-ray matches the CT best {a.orientation.replace('-', ' ')} (GC {best:.2f} against "
                            f"{stored:.2f} as stored): the display is mirrored or rotated; export the image as "
                            "acquired (head up, patient's right on the viewer's left) and register again")
        if state.identification is not None and state.identification.status == "contradicted":
            problems.append(state.identification.message)
        lo_tx, hi_tx = tx_limits(state.geometry, *p.magnification_range)
        if not lo_tx - 1 <= pose.tx_mm <= hi_tx + 1:
            problems.append("the found source-to-detector position is outside the searched range")
        return problems


def _drop_results_from(state: RegistrationState, name: str) -> None:
    """Forget the results of ``name`` and every later stage, so a re-run stage never sees stale poses."""
    later = STAGES[STAGES.index(name):]
    fields = {"database": ("database",), "spatial": ("spatial",), "depth": ("depth",), "fine": ("fine",),
              "refine": ("refine", "refined_pose"), "levels": ("identification",), "final_drr": ("drr_line_integral",)}
    for stage in later:
        for attribute in fields[stage]:
            setattr(state, attribute, None)
    if "levels" in later:  # the pairs the levels stage chose are its result too
        state.pairs = state.given_pairs
    if "spatial" in later:  # the polarity the spatial stage found, and the attenuation image built with it
        state.appearance = _initial_appearance(state.xray, state.parameters)
        state.xray_line_integral = attenuation(state.xray.pixels, state.mask, state.appearance.bone_dark,
                                               state.appearance.storage)
    state.stages = [s for s in state.stages if s.name not in later]


def _chosen_fit(state: RegistrationState) -> LabellingFit | None:
    """The levels stage's fit of the labelling the registration continues with (None without one)."""
    ident = state.identification
    if ident is None or ident.mode == "image_only" or state.pairs is None:
        return None
    fit = ident.chosen
    return fit if fit.labels == list(state.pairs.labels) and fit.depth is not None else None


def _initial_appearance(xray: XrayImage, params: RegistrationParameters) -> Appearance:
    """The appearance before the spatial stage finds it: the user's polarity, else the file's."""
    return fixed_appearance(params.polarity, xray.bone_dark, xray.sources.get("bone_dark", ""))


def _name_margins(ident: LevelIdentification | None) -> dict[str, float]:
    """Per level named by the levels stage, how far its labelling is ahead of the best other one (every other
    labelling renames every click, so it is the labelling's margin)."""
    if ident is None:
        return {}
    labels = ident.visible_labels if ident.mode == "image_only" else ident.chosen.labels
    return {lb: float(ident.margin) for lb in labels}


def _in_image(uv: np.ndarray, size_px: tuple[int, int]) -> bool:
    return bool(-0.5 <= uv[0] <= size_px[0] - 0.5 and -0.5 <= uv[1] <= size_px[1] - 0.5)


def _given_pairs(ct_landmarks: Landmarks3D, xray_landmarks: Landmarks2D) -> tuple[Pairs | None, list[str]]:
    """Pairs by name when every click is named (LandmarkError with fewer than ``MIN_CLICKS`` common levels);
    None when some clicks are unnamed (at least ``MIN_CLICKS`` of them) or there are none. Also the
    plausibility notes."""
    n = len(xray_landmarks.labels)
    if n and xray_landmarks.named:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            pairs = pair_by_label(ct_landmarks, xray_landmarks, MIN_CLICKS)
        return pairs, [str(w.message) for w in caught]
    if 0 < n < MIN_CLICKS:
        raise LandmarkError(f"only {n} X-ray click(s): click the centres of at least {MIN_CLICKS} adjacent "
                            "vertebrae (named or not), or none to identify the levels from the image alone")
    if n:  # unnamed or partly named: refuse now, not after the database, what no labelling can satisfy
        check_labelling_possible(xray_landmarks, ct_level_names(ct_landmarks))
    return None, spine_order_warnings(ct_landmarks)


def _check_landmarks(ct: Volume, ct_landmarks: Landmarks3D, xray: XrayImage, clicks: Landmarks2D) -> None:
    """Refuse points outside the CT or the image, and degenerate (coincident) point sets."""
    outside = [lb for lb, inside in zip(ct_landmarks.labels, ct.contains_lps(ct_landmarks.points_lps_mm),
                                        strict=True) if not inside]
    if outside:
        raise LandmarkError(f"CT landmark(s) {', '.join(outside)} in {ct_landmarks.source or 'the CT landmarks'} "
                            f"lie outside the CT volume {ct.source}: check the landmark file's coordinate system "
                            "(LPS vs RAS) and that it belongs to this CT")
    cols, rows = xray.size_px
    used = identifiable_clicks(clicks, ct_level_names(ct_landmarks))
    uv_all = np.asarray(clicks.uv_px, float).reshape(-1, 2)[used]
    off = [clicks.labels[i] or f"unnamed click {i + 1}" for i, uv in zip(used, uv_all, strict=True)
           if not _in_image(uv, (cols, rows))]
    if off:
        raise LandmarkError(f"X-ray landmark(s) {', '.join(off)} lie outside the {cols}x{rows} image "
                            f"{xray.source}: check they are (column, row) pixels of this X-ray")
    if len(ct_landmarks.labels) < 3:
        raise LandmarkError(f"only {len(ct_landmarks.labels)} CT centroid(s) in {ct_landmarks.source or 'the CT'}: "
                            "label at least 3 vertebrae in the CT")
    for name, pts in (("CT", ct_landmarks.points_lps_mm), ("X-ray", uv_all)):
        if len(pts) < 2:
            continue
        d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(len(pts)) * 1e9
        if d.min() < 1.0:
            raise LandmarkError(f"two {name} landmarks are less than 1 {'mm' if name == 'CT' else 'px'} apart: "
                                "each level needs its own centroid")
