"""The outcome of a registration (``build_result``): the final pose, every CT level projected on the X-ray (pixel
(column, row), clicked levels with their projection distance in detector mm), the level check, and the checks
that make ``ok`` False with the reason in words (``result_problems``). On a detector with radial distortion
(``geometry.distortion``) the levels and clicks are given where the X-ray shows them, the projection distances
between the pinhole projection and the click's ideal point.

An X-ray refused for its display (``refused_display``: it matches the CT best mirrored or turned) names no level:
its level check is ``withheld_for`` that reason, since a pose and names found on the image as stored are a guess
under the wrong geometry (the appearance benchmark's mirrored displays: named right about half the time).
"""

from __future__ import annotations

from carmreg.logic.geometry.camera import CarmPose, in_detector, project
from carmreg.logic.geometry.projection_distance import pde_mm
from carmreg.logic.image.field import field_record
from carmreg.logic.image.turn import composed, turn_advice
from carmreg.logic.io.landmarks import level_index
from carmreg.logic.registration.depth import tx_limits
from carmreg.logic.registration.levels import (
    LevelIdentification,
)
from carmreg.logic.registration.state import RegistrationResult, RegistrationState


def build_result(state: RegistrationState) -> RegistrationResult:
    """The registration's outcome from its state: pose, every CT level projected (clicked ones with their PDE),
    the level check, and ``ok`` with the reasons when a check fails (``result_problems``)."""
    pose = CarmPose.from_array(state.pose)
    P = state.geometry.projection_matrix(pose)
    intr = state.geometry.intrinsics
    warp = intr.distortion
    fitted = set(state.pairs.labels) if state.pairs is not None else set()
    clicked = dict(zip(state.pairs.labels, state.pairs.uv_px, strict=True)) if state.pairs is not None else {}
    named = name_margins(state.identification)
    levels = []
    for label, point in sorted(state.ct_landmarks.as_dict().items(), key=lambda kv: level_index(kv[0])):
        uv = warp.distort(project(P, point[None])[0])  # where the X-ray shows it
        pde = float(pde_mm(P, point[None], clicked[label][None], intr.pixel_spacing_mm)[0]) \
            if label in clicked else None
        levels.append({"label": label, "uv_px": [float(uv[0]), float(uv[1])], "fitted": label in fitted,
                       "pde_mm": pde, "in_image": in_detector(uv, intr.size_px),
                       "clicked_uv_px": [float(x) for x in warp.distort(clicked[label])]
                       if label in clicked else None,
                       "name_margin": named.get(label)})
    problems = result_problems(state, pose)
    check = level_check(state)
    warnings = state.warnings + problems
    if check is not None and check.withheld:  # the levels stage's own warning speaks of names no longer given
        warnings = [w for w in warnings if w != state.identification.message]
    spatial = state.spatial
    return RegistrationResult(
        pose=pose, projection_matrix=P, geometry=state.geometry, stages=list(state.stages), levels=levels,
        drr_line_integral=state.drr_line_integral, xray_line_integral=state.xray_line_integral,
        convergence=state.fine.convergence if state.fine else [],
        trajectory=state.fine.trajectory if state.fine else [],
        similarity_maps=spatial.maps if spatial else {},
        database_grid={"ty_mm": state.database.ty_mm.tolist(), "tz_mm": state.database.tz_mm.tolist()}
        if state.database else {},
        ok=not problems, warnings=warnings, failed_checks=list(problems), parameters=state.parameters,
        level_check=check,
        appearance=state.appearance, field_mask=state.mask,
        inputs={"ct": state.ct.source, "xray": state.xray.source, "ct_landmarks": state.ct_landmarks.source,
                "xray_landmarks": state.xray_landmarks.source, "geometry_sources": geometry_sources(state),
                "xray_frame": state.xray.meta.get("frame"), "xray_turned": xray_turned(state),
                "xray_field": field_record(state.mask, state.round_field, state.parameters.xray_field),
                "xray_frames_in_file": state.xray.meta.get("n_frames")})


def xray_turned(state: RegistrationState) -> str:
    """The orientation the user had the X-ray turned by before registering (``image.turn.turned_xray``)."""
    return state.xray.meta.get("turned", "as-stored")


def geometry_sources(state: RegistrationState) -> dict:
    """Where each geometry value came from (the X-ray's reader), the pincushion from the refine stage's estimate
    when the detector took it (``pipeline.take_pincushion``)."""
    sources = dict(state.xray.sources)
    if state.pinhole is not None:
        sources["distortion_mm"] = state.geometry.intrinsics.sources["distortion_mm"]
    return sources


def level_check(state: RegistrationState):
    """The levels stage's answer as recorded (``LevelIdentification.summary``), its names withheld when the
    X-ray's display is refused (``refused_display``); None when the stage did not run."""
    if state.identification is None:
        return None
    check, refused = state.identification.summary(), refused_display(state.appearance, xray_turned(state))
    return check.withheld_for(refused) if refused else check


def refused_display(a, turned: str = "as-stored") -> str:
    """Why the X-ray is refused, in words, when its appearance ``a`` matches the CT best mirrored or turned
    (``image.appearance``: ``orientation`` other than as given); "" otherwise. ``turned``: the turn the user had the
    file turned by (``xray_turned``); the turn advised is the file's (``advised_turn``)."""
    if a is None or a.orientation == "as-stored":
        return ""
    best, given = a.orientation_gc()
    as_given = "as stored" if turned == "as-stored" else f"shown {turned.replace('-', ' ')} as asked"
    advice = turn_advice(advised_turn(a, turned))
    return (f"the X-ray matches the CT best {a.orientation.replace('-', ' ')} (GC {best:.2f} against {given:.2f} "
            f"{as_given}): the display is mirrored or rotated; export the image as acquired (head up, patient's "
            f"right on the viewer's left) and register again{advice}")


def advised_turn(a, turned: str = "as-stored") -> str | None:
    """The turn of the file (``image.turn.ORIENTATIONS``) that shows it as the CT matches it, when appearance ``a``
    refuses the display (``refused_display``): the user's ``turned``, then the one the image matches in
    (``image.turn.composed``; a quarter turn and a mirror make a transpose, which the user can turn back too). None
    when the display is not refused."""
    if a is None or a.orientation == "as-stored":
        return None
    return composed(turned, a.orientation)


def result_problems(state: RegistrationState, pose: CarmPose) -> list[str]:
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
    refused = refused_display(state.appearance, xray_turned(state))
    if refused:
        problems.append(refused)
    if not refused and state.identification is not None and state.identification.status == "contradicted":
        problems.append(state.identification.message)
    lo_tx, hi_tx = tx_limits(state.geometry, *p.magnification_range)
    if not lo_tx - 1 <= pose.tx_mm <= hi_tx + 1:
        problems.append("the found source-to-detector position is outside the searched range")
    return problems


def name_margins(ident: LevelIdentification | None) -> dict[str, float]:
    """Per level named by the levels stage, how far its labelling is ahead of the best other one (every other
    labelling renames every click, so it is the labelling's margin)."""
    if ident is None:
        return {}
    labels = ident.visible_labels if ident.mode == "image_only" else ident.chosen.labels
    return {lb: float(ident.margin) for lb in labels}


