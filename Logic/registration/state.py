"""What the stages share: the registration's parameters, its state filled stage by stage, each stage's result and
the final ``RegistrationResult`` (pose, levels, level check, ``ok``). Stage order ``STAGES``; re-running a stage
forgets its result and every later one (``drop_results_from``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from carmreg.logic.geometry.camera import CarmGeometry, CarmPose
from carmreg.logic.geometry.volume import MuPyramid, Volume
from carmreg.logic.image.appearance import (
    Appearance,
    fixed_appearance,
)
from carmreg.logic.image.prepare import attenuation
from carmreg.logic.io.landmarks import Landmarks2D, Landmarks3D, Pairs
from carmreg.logic.io.xray import XrayImage
from carmreg.logic.registration.click_polarity import ClickPolarity
from carmreg.logic.registration.database import DrrDatabase
from carmreg.logic.registration.depth import DepthResult
from carmreg.logic.registration.fine import FineParameters, FineResult
from carmreg.logic.registration.image_polarity import ImagePolarity
from carmreg.logic.registration.image_refine import RefineParameters, RefineResult
from carmreg.logic.registration.labelling_fit import LabellingFit, coarse_refine_parameters
from carmreg.logic.registration.labelling_order import LabellingOrders
from carmreg.logic.registration.level_check import LevelCheck
from carmreg.logic.registration.levels import (
    IdentifyParameters,
    LevelIdentification,
)
from carmreg.logic.registration.pincushion import UNCORRECTED_INTENSIFIER
from carmreg.logic.registration.refinement_memo import RefinementMemo
from carmreg.logic.registration.spatial import SpatialResult

STAGES = ("database", "spatial", "levels", "depth", "fine", "refine", "final_drr")

@dataclass
class RegistrationParameters:
    """Every choice of the pipeline, with the paper's value where it gives one."""

    metric: str = "gc"                      # spatial-search metric (paper: PSNR); see README for why GC
    polarity: str = "auto"                  # auto (found from the image) | bone-dark | bone-bright
    storage: str = "auto"                   # a bone-dark image's: auto (the file's, else found from the image) |
    #                                         linear-intensity | log-display (``image.prepare.STORAGES``)
    xray_field: str = "auto"                # the X-ray's exposed field: auto (found, ``image.field``) | whole
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
    nominal_depth_start: bool = True        # with clicks: the coarse pass also refined from the clicks' fit at
    #                                         the nominal depth (``labelling_fit.refit_at_nominal_depth``)
    estimate_pincushion: bool = True        # a round field without a distortion calibration: its pincushion
    #                                         estimated from the image by the refine stage (``pincushion``)
    level_check: bool = True                # named clicks: also try the names shifted +-1, +-2 levels
    identify: IdentifyParameters = field(default_factory=IdentifyParameters)
    final_drr_max_px: int = 1024            # final DRR detector size cap (longest side)
    final_drr_rays_per_voxel: float = 2.0   # ... and no finer than this many rays per CT voxel at the isocentre
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
    known_gc: np.ndarray | None = None      # GC of the chosen conversion with every DRR, if already computed
    click_polarity: ClickPolarity | None = None  # the polarity check's registrations at the clicks (spatial stage)
    image_polarity: ImagePolarity | None = None  # ... and without clicks, on the image alone (spatial stage)
    turned_fits: dict = field(default_factory=dict)  # the orientation check's registrations, per (polarity, storage)
    refinements: RefinementMemo = field(default_factory=RefinementMemo)  # labellings' refinements run so far
    labelling_orders: LabellingOrders = field(default_factory=LabellingOrders)  # unnamed clicks' labellings' order
    given_pairs: Pairs | None = None        # the clicks as named by the surgeon (all named), else None
    round_field: bool = False               # the exposed field is a disc (an image intensifier's: ``field``)
    pinhole: tuple | None = None            # (geometry, pairs, the estimate's note) before the refine stage's
    #                                         pincushion estimate (``pincushion``) took over; None: none taken
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
    warnings: list                  # every message: advisories and the failed checks
    parameters: RegistrationParameters
    inputs: dict = field(default_factory=dict)
    level_check: LevelCheck | None = None  # the level answer (registration.level_check); None: not checked
    appearance: Appearance | None = None  # the X-ray's polarity and storage, and the evidence
    field_mask: np.ndarray | None = None  # (rows, cols) exposed field of the X-ray
    failed_checks: list = field(default_factory=list)  # the messages that make ``ok`` False (also in warnings)

    @property
    def xray_turned(self) -> str:
        """The orientation the user had the X-ray turned by before registering (``image.turn``; "as-stored")."""
        return self.inputs.get("xray_turned", "as-stored")

    @property
    def magnification(self) -> float:
        return float(self.geometry.magnification(self.pose))




def drop_results_from(state: RegistrationState, name: str) -> None:
    """Forget the results of ``name`` and every later stage, so a re-run stage never sees stale poses."""
    later = STAGES[STAGES.index(name):]
    if "refine" in later and state.pinhole is not None:  # the detector as prepared, before the estimated pincushion
        state.geometry, state.pairs, note = state.pinhole
        state.warnings[:] = [UNCORRECTED_INTENSIFIER if w == note else w for w in state.warnings]
        state.pinhole = None
    fields = {"database": ("database",), "spatial": ("spatial", "click_polarity", "image_polarity"),
              "depth": ("depth",), "fine": ("fine",), "refine": ("refine", "refined_pose"),
              "levels": ("identification",), "final_drr": ("drr_line_integral",)}
    for stage in later:
        for attribute in fields[stage]:
            setattr(state, attribute, None)
    if "levels" in later:  # the pairs the levels stage chose are its result too
        state.pairs = state.given_pairs
    if "spatial" in later:  # the polarity the spatial stage found, and the attenuation image built with it
        state.appearance = initial_appearance(state.xray, state.parameters)
        state.xray_line_integral = attenuation(state.xray.pixels, state.mask, state.appearance.bone_dark,
                                               state.appearance.storage)
        state.turned_fits = {}
    state.stages = [s for s in state.stages if s.name not in later]


def chosen_fit(state: RegistrationState) -> LabellingFit | None:
    """The levels stage's fit of the labelling the registration continues with (None without one)."""
    ident = state.identification
    if ident is None or ident.mode == "image_only" or state.pairs is None:
        return None
    fit = ident.chosen
    return fit if fit.names(state.pairs.labels) and fit.depth is not None else None


def initial_appearance(xray: XrayImage, params: RegistrationParameters) -> Appearance:
    """The appearance before the spatial stage finds it: the user's polarity, else the file's."""
    return fixed_appearance(params.polarity, xray.bone_dark, xray.sources.get("bone_dark", ""))
