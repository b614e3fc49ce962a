"""Write a registration result: result.json, overlay, DRR (PNG + NRRD with geometry), .tfm, figures.

Files (written into ``out_dir`` as one transaction, see ``carmreg.logic.io.transaction``; plus its
``carmreg-manifest.json`` naming and checksumming every file):
- ``result.json``: ``ok`` and ``warnings``; ``level_check`` (which vertebra is which: the mode - named,
  partly_named, unnamed or image_only -, the names assigned to the clicks, the winner and runner-up labellings,
  the margin between them and the status confident / ambiguous / contradicted / proposed (no clicks); see
  ``level_identify``);
  ``projection_matrix`` (3x4, LPS mm -> homogeneous (column, row) px);
  ``pose`` (the 6 C-arm parameters, mm and degrees, about the nominal AP pose described in ``geometry``);
  ``geometry`` (intrinsics, isocentre, SOD, the radial distortion ``distortion_mm`` given or estimated (0 = none;
  levels and clicks are then where the X-ray shows them, ``projection_matrix`` the pinhole before it), where each
  value came from); per-stage mPDE (detector mm), seconds
  and choices; ``levels`` (every CT-labelled level's projected ``uv_px``, fitted or not, PDE when clicked);
  ``parameters``; ``reproducibility`` (versions, seed).
- ``overlay.png``: the overlay as the window shows it by default and the report page prints it
  (``report.overlay``: the X-ray bone bright with the DRR blended in amber, every CT-labelled level projected and
  named - fitted levels as filled green discs with their PDE, red with a "?" when the image contradicts the
  names, the others as yellow rings, clicks as red crosses - and the level answer's banner across the top, in
  the colours of ``report.style``), at the X-ray's size.
- ``drr.png`` (attenuation, bone bright) and ``drr.nrrd`` (float32 line integrals; a 3D one-slice volume on
  the detector plane in LPS: ``space origin`` = detector pixel (0, 0), ``space directions`` = one pixel step
  along columns and rows, then the detector normal; it opens in 3D Slicer in place).
- ``carm.tfm``: ITK affine, the rigid transform lps_to_camera (see ``transform_io``).
- ``convergence.png`` (paper Fig. 9-10) and ``similarity_maps.png`` (paper Fig. 6).
- ``report.pdf``: the one-page report (``report.page``).
- ``slicer/CarmReg.mrml`` and its files, when the CT is given: a 3D Slicer scene (see ``slicer_scene``).
"""

from __future__ import annotations

import io
import platform
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from PIL import Image

from carmreg.logic import __version__
from carmreg.logic.errors import CarmRegError
from carmreg.logic.geometry.camera import pixel_to_detector_lps
from carmreg.logic.geometry.distortion import DISTORTION_MODEL
from carmreg.logic.io.atomic import atomic_write, atomic_write_bytes, atomic_write_json, to_jsonable
from carmreg.logic.io.transaction import FolderTransaction
from carmreg.logic.report.overlay import result_overlay_image

__all__ = ["FIGURE_FILES", "RESULT_FILES", "figures", "result_dict", "save_png", "save_result", "to_uint8",
           "write_drr_nrrd"]


def result_dict(result) -> dict:
    """JSON-ready summary of a RegistrationResult; a value that is not a finite number (a margin with no rival
    labelling to measure it against is inf) is written as null."""
    import numba
    import scipy

    g = result.geometry
    intr = g.intrinsics
    return to_jsonable({
        "ok": bool(result.ok),
        "warnings": list(result.warnings),
        "failed_checks": list(getattr(result, "failed_checks", [])),
        "projection_matrix": np.asarray(result.projection_matrix, float).tolist(),
        "projection_convention": "homogeneous LPS mm -> homogeneous (column, row) px; 0-based pixel centres",
        "pose": result.pose.as_dict(),
        "magnification": result.magnification,
        "source_lps_mm": g.source_lps_mm(result.pose).tolist(),
        "geometry": {"sdd_mm": intr.sdd_mm, "pixel_spacing_mm": list(intr.pixel_spacing_mm),
                     "size_px": list(intr.size_px), "principal_point_px": list(intr.principal_point_px),
                     "isocenter_lps_mm": list(g.isocenter_lps_mm), "sod_mm": g.sod_mm,
                     "distortion_mm": intr.distortion_mm, "distortion_k_per_mm2": intr.distortion.k_per_mm2,
                     "distortion_model": DISTORTION_MODEL,
                     "sources": dict(result.inputs.get("geometry_sources", {}))},
        "stages": [{"name": s.name, "mpde_mm": s.mpde_mm, "seconds": round(s.seconds, 4),
                    "pose": s.pose.as_dict(), **to_jsonable(s.extra)} for s in result.stages],
        "levels": result.levels,
        "level_check": to_jsonable(result.level_check),
        "appearance": to_jsonable(result.appearance.as_dict()) if result.appearance is not None else None,
        "parameters": to_jsonable(result.parameters.as_dict()),
        "inputs": result.inputs,
        "reproducibility": {"carmreg": __version__, "python": platform.python_version(),
                            "numpy": np.__version__, "scipy": scipy.__version__,
                            "numba": numba.__version__, "seed": result.parameters.fine.seed},
    })


def to_uint8(image: np.ndarray, mask: np.ndarray | None = None, percentiles=(0.5, 99.5)) -> np.ndarray:
    """Window an image to 0..255 by percentiles (inside ``mask`` when given)."""
    vals = image[mask] if mask is not None and mask.any() else image.ravel()
    lo, hi = np.percentile(vals, percentiles)
    return (np.clip((image - lo) / max(hi - lo, 1e-9), 0, 1) * 255).astype(np.uint8)


PNG_COMPRESS_LEVEL = 1
"""zlib level of the PNGs written (measured on a 960 px overlay: 0.08 s and 670 kB, against 0.24 s and 560 kB at
PIL's default 6)."""


def save_png(path: str | Path, image: Image.Image | np.ndarray) -> Path:
    img = image if isinstance(image, Image.Image) else Image.fromarray(image)
    return atomic_write(path, lambda tmp: img.save(tmp, format="PNG", compress_level=PNG_COMPRESS_LEVEL))


def detector_ijk_to_lps(geometry, pose) -> np.ndarray:
    """4x4 voxel (i, j, k) -> LPS mm of a detector image stored as a one-slice 3D volume.

    i = column u, j = row v (0-based pixel centres), k = 0 the detector plane: column 0 is the LPS position of
    detector pixel (0, 0); column 1 one pixel step along u (du mm, camera x); column 2 one pixel step along v
    (dv mm, camera y); column 3 the slice normal, camera z (source -> detector) scaled to du mm, so the voxel
    axes are right-handed (x cross y = z) and the slice has a thickness Slicer can show.
    """
    corners = pixel_to_detector_lps(geometry, pose, np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
    step_u, step_v = corners[1] - corners[0], corners[2] - corners[0]
    rotation, _ = geometry.extrinsics(pose)
    ijk_to_lps = np.eye(4)
    ijk_to_lps[:3, 0], ijk_to_lps[:3, 1] = step_u, step_v
    ijk_to_lps[:3, 2] = rotation[2] * np.linalg.norm(step_u)  # camera z in LPS = third row of lps->camera R
    ijk_to_lps[:3, 3] = corners[0]
    return ijk_to_lps


def write_detector_nrrd(path: str | Path, image: np.ndarray, geometry, pose, content: str,
                        dtype=np.float32) -> Path:
    """A detector image ``image[row, column]`` as a 3D one-slice NRRD in LPS (see ``detector_ijk_to_lps``).

    3D Slicer's volume reader refuses a 2D image embedded in 3D space; the same pixels as a (columns, rows, 1)
    volume load, in place on the detector plane in the CT's frame. The header also carries the 3x4
    ``projection_matrix`` (LPS mm -> homogeneous (column, row) px) of the pose.
    """
    import nrrd

    ijk_to_lps = detector_ijk_to_lps(geometry, pose)
    header = {"space": "left-posterior-superior", "space origin": ijk_to_lps[:3, 3],
              "space directions": ijk_to_lps[:3, :3].T.copy(), "kinds": ["domain", "domain", "domain"],
              "encoding": "gzip",
              "projection_matrix": " ".join(f"{x:.9g}" for x in
                                            np.asarray(geometry.projection_matrix(pose)).ravel()),
              "content": content}
    data = np.ascontiguousarray(np.asarray(image, dtype).T[:, :, None])  # nrrd axis 0 fastest = columns
    return atomic_write(path, lambda tmp: nrrd.write(str(tmp), data, header, compression_level=1))


def write_drr_nrrd(path: str | Path, line_integral: np.ndarray, geometry, pose) -> Path:
    """The DRR's float32 line integrals on the detector plane (``write_detector_nrrd``)."""
    return write_detector_nrrd(path, line_integral, geometry, pose,
                               "CarmReg DRR line integral (dimensionless); axis 0 = column u, axis 1 = row v, "
                               "axis 2 = one slice on the detector plane")


def _figure(size_inches: tuple[float, float]):
    """A matplotlib Figure on an Agg canvas (no pyplot: no global figure to close, no GUI backend)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size_inches)
    FigureCanvasAgg(fig)
    return fig


def _figure_bytes(fig) -> bytes:
    """The figure as PNG bytes at 110 dpi, laid out by its own margins (``bbox_inches="tight"`` would draw it twice
    to find them: 0.12 s more for the convergence plot)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    return buf.getvalue()


def convergence_figure(result) -> bytes:
    """mPDE over evaluations and the pose parameters' trajectory (paper Fig. 9-10). Left: the detector mPDE at the
    pose of the best objective so far (``fine.objective`` adds a rotation prior to the mPDE, so this can rise while
    the objective falls). Right: the fine search's mean minus the fine stage's own answer (``fine_stage_pose``), so
    the curves settle at 0; the image refinement moves the final pose on from there."""
    fig = _figure((10, 3.6))
    a, b = fig.subplots(1, 2, gridspec_kw={"wspace": 0.3})
    fig.subplots_adjust(left=0.09, right=0.985, bottom=0.13, top=0.92)
    if result.convergence:
        ev, m, _ = np.array(result.convergence).T
        a.semilogy(ev, np.maximum(m, 1e-3), color="tab:blue")
    a.set(xlabel="evaluations", ylabel="mPDE at the best pose so far (mm)", title="Fine stage: mPDE")
    if result.trajectory:
        ev = np.array([t[0] for t in result.trajectory])
        poses = np.array([t[1] for t in result.trajectory])
        answer = fine_stage_pose(result)
        names = ["tx mm", "ty mm", "tz mm", "rx deg", "ry deg", "rz deg"]
        for k in range(6):
            b.plot(ev, poses[:, k] - answer[k], label=names[k])
        b.legend(fontsize=7, ncol=2)
    b.set(xlabel="evaluations", ylabel="mean - fine-stage pose", title="Fine stage: parameters")
    return _figure_bytes(fig)


def fine_stage_pose(result) -> np.ndarray:
    """(6,) pose the fine stage answered (its ``StageResult``); the final pose when that stage is not recorded."""
    fine = next((s.pose for s in result.stages if s.name == "fine"), result.pose)
    return fine.as_array()


def similarity_figure(result) -> bytes:
    """One panel per metric: similarity over (ty, tz), the chosen metric's best marked (paper Fig. 6)."""
    maps = result.similarity_maps
    ty, tz = np.array(result.database_grid.get("ty_mm", [0])), np.array(result.database_grid.get("tz_mm", [0]))
    width_inches = 2.6 * max(1, len(maps))
    fig = _figure((width_inches, 3.4))
    axes = fig.subplots(1, max(1, len(maps)), squeeze=False)
    fig.subplots_adjust(left=0.8 / width_inches, right=1 - 0.1 / width_inches, bottom=0.14, top=0.91, wspace=0.35)
    for ax, (name, m) in zip(axes[0], maps.items(), strict=False):
        ax.imshow(m.T, origin="lower", aspect="auto", extent=[ty[0], ty[-1], tz[0], tz[-1]], cmap="viridis")
        iy, iz = np.unravel_index(int(np.argmax(m)), m.shape)
        ax.plot(ty[iy], tz[iz], "r+", ms=10)
        ax.set(title=name.upper(), xlabel="ty mm")
    axes[0][0].set_ylabel("tz mm")
    return _figure_bytes(fig)


RESULT_FILES = ("result.json", "overlay.png", "drr.png", "drr.nrrd", "carm.tfm", "convergence.png",
                "similarity_maps.png", "slicer", "report.pdf")
"""Every name ``save_result`` has written (an old folder's copies are replaced or removed, never kept)."""


def save_result(result, out_dir: str | Path, xray_pixels: np.ndarray, clicked: dict | None = None,
                ct=None, ct_landmarks=None, draw_aside: bool = False) -> dict:
    """Write every output file as one transaction (``FolderTransaction``): ``out_dir`` then holds exactly this
    result's files (and the user's own), or - after a failure, a full disk or a kill at any moment - exactly
    what it held before. Returns {name: final path}. Anything written under ``out`` in ``_write_result_files``
    (subfolders too) goes into the transaction. A failure to write raises CarmRegError naming the folder.

    ``xray_pixels``: the X-ray as stored (shown as stored). Given the CT (``Volume``) and its ``Landmarks3D``,
    also the 3D Slicer scene ``slicer/CarmReg.mrml`` with its files (``slicer_scene``). ``draw_aside``: draw the
    report page and the convergence plot in a forked child process meanwhile (``aside``, ``DRAWN_ASIDE``; the
    command line: ~0.4 s less; the same files, the PDF's creation time aside)."""
    target = Path(out_dir)
    try:
        with FolderTransaction(target, owned_names=RESULT_FILES) as out:
            paths = _write_result_files(result, out, xray_pixels, clicked, ct, ct_landmarks, draw_aside)
    except OSError as exc:
        raise CarmRegError(f"{target}: could not write the results ({exc.strerror or exc}); the folder still "
                           "holds its previous content: free some space or choose another --out") from None
    return {name: target / Path(path).relative_to(out) for name, path in paths.items()}


FIGURE_FILES = {"convergence": "convergence.png", "similarity": "similarity_maps.png", "report": "report.pdf"}
"""The files ``figures`` draws: {key in ``save_result``'s answer: file name}."""


def figures(result, xray_pixels: np.ndarray, clicked: dict | None, keys=tuple(FIGURE_FILES)) -> dict[str, bytes]:
    """{key: the file's bytes} for the ``keys`` of ``FIGURE_FILES``: the convergence plot, the similarity maps
    (when computed) and the report page - everything matplotlib draws but the overlay."""
    from carmreg.logic.report.page import report_pdf_bytes

    draw = {"convergence": lambda: convergence_figure(result),
            "similarity": lambda: similarity_figure(result) if result.similarity_maps else None,
            "report": lambda: report_pdf_bytes(result, xray_pixels, clicked)}
    drawn = {key: draw[key]() for key in keys}
    return {key: data for key, data in drawn.items() if data is not None}


DRAWN_ASIDE = ("convergence", "report")
"""The figures the child draws (``aside``: the report page and the convergence plot, ~0.6 s after importing
matplotlib), while this process draws the overlay and the similarity maps, writes the other files, and a thread
writes the 3D Slicer scene: of the splits tried, the one where both end soonest (the demo's files in 1.5 s
against 1.9 s drawn here, median of 5 alternating runs)."""


def _write_result_files(result, out: Path, xray_pixels: np.ndarray, clicked: dict | None, ct,
                        ct_landmarks, draw_aside: bool = False) -> dict:
    from carmreg.logic.report import aside

    if draw_aside:  # matplotlib (0.3 s to import) imported once, before the fork: both processes draw with it
        import matplotlib.backends.backend_agg  # noqa: F401
        import matplotlib.figure  # noqa: F401
    child = aside.start(figures, result, xray_pixels, clicked, DRAWN_ASIDE) if draw_aside else None
    try:
        return _write_files(result, out, xray_pixels, clicked, ct, ct_landmarks, child)
    finally:
        aside.cancel(child)  # gone already, unless this process stopped first


def _write_files(result, out: Path, xray_pixels: np.ndarray, clicked: dict | None, ct, ct_landmarks,
                 child) -> dict:
    """Every file into ``out``; the figures of ``DRAWN_ASIDE`` from ``child`` when it is given (``aside``)."""
    from carmreg.logic.io.transforms import write_tfm
    from carmreg.logic.report import aside

    paths = {"result": atomic_write_json(out / "result.json", result_dict(result)),
             "overlay": save_png(out / "overlay.png", result_overlay_image(result, xray_pixels, clicked))}
    if result.drr_line_integral is not None:
        paths["drr_png"] = save_png(out / "drr.png", to_uint8(result.drr_line_integral))
        paths["drr_nrrd"] = write_drr_nrrd(out / "drr.nrrd", result.drr_line_integral, result.geometry,
                                           result.pose)
    rotation, t = result.geometry.extrinsics(result.pose)
    lps_to_camera = np.eye(4)
    lps_to_camera[:3, :3], lps_to_camera[:3, 3] = rotation, t
    paths["tfm"] = write_tfm(out / "carm.tfm", lps_to_camera,
                             comment="lps_to_camera: CT LPS mm -> C-arm camera mm (origin at the X-ray source)")
    with ThreadPoolExecutor(max_workers=1) as pool:  # the scene (mostly zlib and file writes, which free the GIL)
        scene = None  # is written while this thread draws the figures (matplotlib holds the GIL): ~0.3 s less
        if ct is not None and ct_landmarks is not None:
            from carmreg.logic.report.slicer_scene import write_slicer_scene
            scene = pool.submit(write_slicer_scene, out, result, ct, ct_landmarks, xray_pixels, clicked,
                                paths.get("drr_nrrd"))
        here = [key for key in FIGURE_FILES if child is None or key not in DRAWN_ASIDE]
        drawn = figures(result, xray_pixels, clicked, here)
        if child is not None:  # the child's figures; those it failed to draw are drawn here (the same figures)
            drawn.update(aside.finish(child) or figures(result, xray_pixels, clicked, DRAWN_ASIDE))
        for key, data in drawn.items():
            paths[key] = atomic_write_bytes(out / FIGURE_FILES[key], data)
        if scene is not None:
            paths.update(scene.result())  # its error, if any, is raised here (inside the folder transaction)
    return paths
