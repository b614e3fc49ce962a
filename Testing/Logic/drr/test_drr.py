"""DRR engines (CPU Siddon and VTK ray casting) against physics and geometry.

A DRR engine is right when (a) a dense bead in an empty volume lands on the pixel P predicts, (b) a homogeneous
slab integrates to mu x thickness / cos(angle), (c) results do not depend on how the volume is stored, and
(d) line integrals match an independent reference. VTK tests are marked ``vtk_render`` and skip when no
OpenGL context can be made (CI runs them under xvfb-run).
"""

import functools
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from carmreg.logic.drr import cpu as drr_cpu
from carmreg.logic.drr.cpu import intensity_from_line_integral, render_line_integrals, transposed_mu
from carmreg.logic.geometry.camera import (
    CarmGeometry,
    CarmIntrinsics,
    CarmPose,
    backproject,
    pixel_to_detector_lps,
    project,
    rotation_matrix,
)
from carmreg.logic.geometry.volume import MuLevel, apply_affine, hu_to_mu

SHARED = Path(__file__).resolve().parents[3].parent / "shared"
REAL_CT = SHARED / "data" / "totalsegmentator-tests" / "example_ct_sm.nii.gz"


# ----------------------------------------------------------------------------------------------------------
# engines


def _vtk_renderer(sample_distance_mm=None):
    from carmreg.logic.drr.vtk_raycast import render_line_integrals_vtk, vtk_rendering_status

    ok, message = vtk_rendering_status()
    if not ok:
        pytest.skip(f"VTK cannot render here (no OpenGL context): {message}")

    def render(level, geometry, poses, intrinsics=None):
        return render_line_integrals_vtk(level, geometry, poses, intrinsics, sample_distance_mm=sample_distance_mm)

    return render


ENGINES = ["cpu", pytest.param("vtk", marks=pytest.mark.vtk_render)]


def engine(name, sample_distance_mm=None):
    return render_line_integrals if name == "cpu" else _vtk_renderer(sample_distance_mm)


# ----------------------------------------------------------------------------------------------------------
# helpers


def affine_from(direction, spacing, origin):
    affine = np.eye(4)
    affine[:3, :3] = np.asarray(direction, float) * np.asarray(spacing, float)
    affine[:3, 3] = origin
    return affine


def centred_affine(shape, spacing, direction=None, centre=(0.0, 0.0, 0.0)):
    """Affine whose voxel-grid centre sits at ``centre`` (LPS mm)."""
    affine = affine_from(np.eye(3) if direction is None else direction, spacing, (0.0, 0.0, 0.0))
    affine[:3, 3] = np.asarray(centre) - apply_affine(affine, (np.asarray(shape) - 1) / 2.0)
    return affine


def pixel_rays_ijk(level, geometry, pose, uv_px, intrinsics=None):
    """(source ijk (3,), pixel-centre ijk (n, 3), ray length mm (n,)) from the public camera functions."""
    g = geometry if intrinsics is None else geometry.with_intrinsics(intrinsics)
    source = g.source_lps_mm(pose)
    pixels = pixel_to_detector_lps(g, pose, np.atleast_2d(uv_px))
    to_ijk = np.linalg.inv(level.ijk_to_lps)
    return (apply_affine(to_ijk, source), apply_affine(to_ijk, pixels),
            np.linalg.norm(pixels - source, axis=1))


def siddon_reference(mu, s, p, length_mm):
    """Straightforward Siddon (1985): all plane crossings, sorted, voxel of each segment midpoint."""
    d = p - s
    alphas = [np.array([0.0, 1.0])]
    for axis in range(3):
        if abs(d[axis]) > 1e-12:
            planes = np.arange(mu.shape[axis] + 1) - 0.5
            alphas.append((planes - s[axis]) / d[axis])
    a = np.concatenate(alphas)
    a = np.unique(np.clip(a, 0.0, 1.0))
    mids = 0.5 * (a[1:] + a[:-1])
    idx = np.floor(s[None] + mids[:, None] * d[None] + 0.5).astype(int)
    inside = np.all((idx >= 0) & (idx < np.array(mu.shape)), axis=1)
    values = np.zeros(len(mids))
    values[inside] = mu[tuple(idx[inside].T)]
    return float((values * np.diff(a)).sum() * length_mm)


def sampled_reference(mu, s, p, length_mm, step_vox=0.005):
    """High-rate midpoint integration of the nearest-neighbour voxel model (step in voxel units)."""
    d = p - s
    n = int(np.ceil(np.linalg.norm(d) / step_vox))
    t = (np.arange(n) + 0.5) / n
    idx = np.floor(s[None] + t[:, None] * d[None] + 0.5).astype(int)
    inside = np.all((idx >= 0) & (idx < np.array(mu.shape)), axis=1)
    return float(mu[tuple(idx[inside].T)].sum() * length_mm / n)


def weighted_centroid_uv(image):
    rows, cols = np.indices(image.shape)
    w = image / image.sum()
    return np.array([(w * cols).sum(), (w * rows).sum()])


def gaussian_bead_level(centre_lps, sigma_mm=1.2, size=64, spacing=0.4):
    """A Gaussian bead in an empty, obliquely stored volume (no ray runs along a voxel axis)."""
    shape = (size, size, size)
    affine = centred_affine(shape, (spacing,) * 3, direction=rotation_matrix([1, 2, 2], 20.0),
                            centre=centre_lps + np.array([1.3, -0.7, 0.9]))
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    r2 = ((apply_affine(affine, ijk) - centre_lps) ** 2).sum(-1)
    return MuLevel(np.ascontiguousarray(0.5 * np.exp(-0.5 * r2 / sigma_mm**2), dtype=np.float32), affine, None)


def real_ct_level():
    nib = pytest.importorskip("nibabel")
    if not REAL_CT.exists():
        pytest.skip(f"real CT not found at {REAL_CT}")
    image = nib.load(str(REAL_CT))
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ image.affine  # NIfTI RAS -> LPS
    mu = hu_to_mu(np.asarray(image.dataobj))
    return MuLevel(np.ascontiguousarray(mu), affine, None)


def ct_geometry(level, size=64, detector_mm=300.0):
    shape = np.array(level.mu_per_mm.shape)
    centre = apply_affine(level.ijk_to_lps, (shape - 1) / 2.0)
    intr = CarmIntrinsics(1020.0, (detector_mm / size,) * 2, (size, size))
    return CarmGeometry(intr, tuple(centre), 600.0)


# ----------------------------------------------------------------------------------------------------------
# (a) a bead lands where P predicts


BEAD_LPS = np.array([4.0, -6.0, 3.0])
BEAD_POSES = [CarmPose(), CarmPose(40.0, -15.0, -2.0, 7.0, -9.0, 25.0), CarmPose(-30.0, -4.0, 5.0, -12.0, 6.0, -40.0)]


@pytest.mark.parametrize("name", ENGINES)
def test_gaussian_bead_centroid_is_projected_centre(name):
    render = engine(name, sample_distance_mm=0.1)
    level = gaussian_bead_level(BEAD_LPS)
    intr = CarmIntrinsics(1000.0, (1.0, 1.2), (60, 48), principal_point_px=(27.0, 21.5))
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 600.0)
    tolerance_px = 0.05 if name == "cpu" else 0.25
    for pose in BEAD_POSES:
        image = render(level, geometry, pose)
        predicted = project(geometry.projection_matrix(pose), BEAD_LPS[None])[0]
        assert np.all(np.abs(predicted - [30, 24]) < 20), "bead must project well inside the image"
        assert np.linalg.norm(weighted_centroid_uv(image) - predicted) < tolerance_px
        # attenuation is conserved: sum(L) * pixel area = sum(mu * voxel volume) * magnification^2
        magnification = geometry.magnification(pose, BEAD_LPS)
        total = level.mu_per_mm.sum(dtype=np.float64) * 0.4**3 * magnification**2 / (1.0 * 1.2)
        assert image.sum(dtype=np.float64) == pytest.approx(total, rel=0.005 if name == "cpu" else 0.01)


def test_a_distorted_detector_shows_a_bead_where_the_distortion_puts_it():
    """An intensifier's pincushion (``CarmIntrinsics.distortion_mm``): the bead's image moves outward to
    ``distort(P x)``, by several pixels 80 mm from the centre; the pinhole's stays at ``P x``."""
    bead = np.array([45.0, -6.0, 20.0])
    level = gaussian_bead_level(bead)
    intr = CarmIntrinsics(1000.0, (1.0, 1.0), (200, 200), distortion_mm=6.0)
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 600.0)
    ideal = project(geometry.projection_matrix(CarmPose()), bead[None])[0]
    shown = intr.distortion.distort(ideal)
    assert 60 < np.linalg.norm(ideal - 99.5) < 90 and np.linalg.norm(shown - ideal) > 2.0
    distorted = render_line_integrals(level, geometry, CarmPose())
    assert np.linalg.norm(weighted_centroid_uv(distorted) - shown) < 0.1
    pinhole = render_line_integrals(level, geometry.with_intrinsics(replace(intr, distortion_mm=0.0)), CarmPose())
    assert np.linalg.norm(weighted_centroid_uv(pinhole) - ideal) < 0.05


def test_the_vtk_engine_refuses_a_distorted_detector():
    from carmreg.logic.drr.vtk_raycast import render_line_integrals_vtk
    from carmreg.logic.errors import GeometryError

    geometry = CarmGeometry(CarmIntrinsics(1000.0, (1.0, 1.0), (50, 50), distortion_mm=2.0), (0.0, 0.0, 0.0), 600.0)
    with pytest.raises(GeometryError, match=r"renders a pinhole camera; .* \(--engine cpu\)"):
        render_line_integrals_vtk(gaussian_bead_level(BEAD_LPS), geometry, CarmPose())


@pytest.mark.parametrize("name", ENGINES)
def test_single_voxel_bead_hits_the_predicted_pixel(name):
    render = engine(name, sample_distance_mm=0.05)
    shape = (31, 31, 31)
    affine = centred_affine(shape, (1.0, 1.0, 1.0), direction=rotation_matrix([1, 1, 0], 20.0))
    mu = np.zeros(shape, np.float32)
    bead_ijk = (17, 13, 16)
    mu[bead_ijk] = 5.0
    level = MuLevel(mu, affine, None)
    bead_lps = apply_affine(affine, bead_ijk)
    intr = CarmIntrinsics(1000.0, (0.5, 0.5), (60, 60), principal_point_px=(28.0, 31.0))
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 700.0)
    poses = (CarmPose(), CarmPose(20.0, -6.0, 0.0, 5.0, -8.0, 20.0), CarmPose(-30.0, -13.0, -3.0, -10.0, 6.0, -35.0))
    for pose in poses:
        image = render(level, geometry, pose)
        predicted = project(geometry.projection_matrix(pose), bead_lps[None])[0]
        col, row = np.round(predicted).astype(int)
        assert 5 <= col < 55 and 5 <= row < 55
        # the ray through the predicted pixel crosses the bead near its middle (>= 0.8 mm of its 1 mm)
        assert image[row, col] >= 5.0 * 0.8
        # nothing lands farther from the prediction than the bead's projected half-diagonal (+ one pixel)
        reach_px = 0.5 * np.sqrt(3.0) * geometry.magnification(pose, bead_lps) / 0.5 + 1.0
        rows, cols = np.nonzero(image > 1e-6)
        assert np.hypot(cols - predicted[0], rows - predicted[1]).max() < reach_px


# ----------------------------------------------------------------------------------------------------------
# (b) a homogeneous slab integrates to mu * thickness / cos(angle)


def slab_case():
    shape = (160, 30, 160)  # 1 mm voxels; the slab spans j = 5..24 -> 20 mm thick along LPS y
    mu = np.zeros(shape, np.float32)
    mu[:, 5:25, :] = 0.02
    affine = centred_affine(shape, (1.0, 1.0, 1.0))
    level = MuLevel(mu, affine, None)
    y_front = apply_affine(affine, [0, 4.5, 0])[1]
    intr = CarmIntrinsics(1000.0, (2.0, 2.0), (48, 40), principal_point_px=(20.0, 22.0))
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 600.0)
    return level, geometry, y_front


@pytest.mark.parametrize("name", ENGINES)
@pytest.mark.parametrize("pose", [CarmPose(), CarmPose(0, 0, 0, 0, 15.0, 30.0), CarmPose(20, 5, -8, 10, -20, -35)])
def test_slab_integrates_mu_thickness_over_cos(name, pose):
    render = engine(name, sample_distance_mm=0.05)
    level, geometry, y_front = slab_case()
    image = render(level, geometry, pose)
    cols, rows = geometry.intrinsics.size_px
    uv = np.stack(np.meshgrid(np.arange(cols), np.arange(rows)), -1).reshape(-1, 2).astype(float)
    source, directions = backproject(geometry, pose, uv)
    cos = np.abs(directions[:, 1])  # slab normal = LPS y
    expected = 0.02 * 20.0 / cos
    # keep rays that cross both faces well inside the slab's lateral extent (|x|, |z| < 70 mm)
    hits = []
    for y in (y_front, y_front + 20.0):
        t = (y - source[1]) / directions[:, 1]
        hits.append(source + t[:, None] * directions)
    inside = np.all([np.all(np.abs(h[:, [0, 2]]) < 70.0, axis=1) for h in hits], axis=0)
    assert inside.mean() > 0.5
    relative = image.reshape(-1)[inside] / expected[inside] - 1.0
    if name == "cpu":
        assert np.abs(relative).max() < 1e-4  # brief: within 0.5 %
    else:
        assert np.abs(relative).max() < 0.01
        assert abs(relative.mean()) < 0.002


# ----------------------------------------------------------------------------------------------------------
# (c) storage does not matter


def phantom_mu(points_lps):
    """A smooth analytic phantom: a few anisotropic Gaussian blobs (1/mm)."""
    blobs = [((0.0, 0.0, 0.0), (12.0, 9.0, 14.0), 0.02), ((10.0, -5.0, 12.0), (4.0, 5.0, 6.0), 0.05),
             ((-12.0, 8.0, -15.0), (6.0, 3.0, 4.0), 0.04)]
    total = np.zeros(points_lps.shape[:-1])
    for centre, sigma, peak in blobs:
        total += peak * np.exp(-0.5 * (((points_lps - centre) / sigma) ** 2).sum(-1))
    return total.astype(np.float32)


def sampled_phantom(shape, affine):
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1)
    return MuLevel(np.ascontiguousarray(phantom_mu(apply_affine(affine, ijk))), affine, None)


ORIENTATION_POSES = [CarmPose(), CarmPose(10.0, 4.0, -6.0, 5.0, 12.0, -20.0)]


def phantom_geometry():
    intr = CarmIntrinsics(1000.0, (3.0, 3.0), (48, 48))
    return CarmGeometry(intr, (0.0, 0.0, 0.0), 600.0)


@functools.lru_cache(maxsize=1)
def straight_and_oblique_phantoms():
    """The same analytic phantom sampled at 1 mm on an axis-aligned grid and on a grid rotated by 30 deg."""
    straight = sampled_phantom((120, 120, 120), centred_affine((120, 120, 120), (1.0, 1.0, 1.0)))
    oblique_direction = rotation_matrix([1, -2, 1], 30.0)
    oblique = sampled_phantom((130, 130, 130), centred_affine((130, 130, 130), (1.0, 1.0, 1.0),
                                                             direction=oblique_direction))
    return straight, oblique


@pytest.mark.parametrize("name", ENGINES)
def test_oblique_storage_gives_the_same_drr(name):
    render = engine(name)
    geometry = phantom_geometry()
    straight, oblique = straight_and_oblique_phantoms()
    for pose in ORIENTATION_POSES:
        a, b = render(straight, geometry, pose), render(oblique, geometry, pose)
        # nearest-neighbour interpolation error of two 1 mm samplings (largest when rays run along a grid axis)
        assert np.abs(a - b).mean() < 0.005 * a.max()
        assert np.abs(a - b).max() < 0.04 * a.max()


def test_permuted_and_flipped_storage_is_exact():
    geometry = phantom_geometry()
    shape = (60, 50, 40)
    affine = centred_affine(shape, (1.6, 1.8, 2.0))
    level = sampled_phantom(shape, affine)
    # the same voxels stored as [k, i, j] with i and k reversed
    perm, mu = (2, 0, 1), level.mu_per_mm
    stored = np.ascontiguousarray(mu[::-1, :, ::-1].transpose(perm))
    flip = np.eye(4)
    flip[0, 0], flip[0, 3] = -1.0, shape[0] - 1
    flip[2, 2], flip[2, 3] = -1.0, shape[2] - 1
    to_old = np.zeros((4, 4))
    to_old[3, 3] = 1.0
    for new_axis, old_axis in enumerate(perm):
        to_old[old_axis, new_axis] = 1.0
    other = MuLevel(stored, affine @ flip @ to_old, None)
    for pose in ORIENTATION_POSES:
        a, b = render_line_integrals(level, geometry, pose), render_line_integrals(other, geometry, pose)
        assert np.allclose(a, b, rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------------------------------------
# (d) line integrals against independent references


def random_level(seed=0):
    rng = np.random.default_rng(seed)
    shape = (23, 17, 11)
    mu = rng.uniform(0.0, 0.05, shape).astype(np.float32)
    mu[rng.uniform(size=shape) < 0.3] = 0.0
    direction = rotation_matrix([2, -1, 3], 35.0) @ np.diag([1.0, 1.0, -1.0])
    return MuLevel(mu, centred_affine(shape, (1.1, 0.9, 2.3), direction=direction), None)


@pytest.mark.parametrize("serial_limit", [0, 10**12], ids=["parallel", "serial"])
def test_cpu_matches_straightforward_siddon(serial_limit, monkeypatch):
    monkeypatch.setattr(drr_cpu, "SERIAL_WORK_LIMIT", serial_limit)
    level = random_level()
    intr = CarmIntrinsics(900.0, (2.0, 2.5), (24, 20), principal_point_px=(10.0, 11.0))
    geometry = CarmGeometry(intr, (1.0, -2.0, 3.0), 500.0)
    for pose in (CarmPose(), CarmPose(12.0, -3.0, 4.0, 20.0, -30.0, 45.0)):
        image = render_line_integrals(level, geometry, pose)
        uv = np.stack(np.meshgrid(np.arange(24), np.arange(20)), -1).reshape(-1, 2).astype(float)
        s, pixels, lengths = pixel_rays_ijk(level, geometry, pose, uv)
        reference = np.array([siddon_reference(level.mu_per_mm, s, p, n) for p, n in zip(pixels, lengths,
                                                                                           strict=True)])
        assert (reference > 0).mean() > 0.3
        assert np.allclose(image.reshape(-1), reference, rtol=1e-4, atol=1e-4 * reference.max())


@pytest.mark.parametrize("name", ENGINES)
def test_real_ct_rays_match_dense_sampling(name):
    render = engine(name)
    level = real_ct_level()
    geometry = ct_geometry(level)
    pose = CarmPose(5.0, 10.0, -5.0, 3.0, -4.0, 10.0)
    image = render(level, geometry, pose)
    uv = np.array([[32, 32], [20, 30], [45, 33], [31, 22], [33, 42], [12, 40], [50, 24], [27, 44]], float)
    s, pixels, lengths = pixel_rays_ijk(level, geometry, pose, uv)
    for (u, v), p, n in zip(uv.astype(int), pixels, lengths, strict=True):
        reference = sampled_reference(level.mu_per_mm, s, p, n)
        assert reference > 0.5  # rays through the body
        assert image[v, u] == pytest.approx(reference, rel=0.01)
        if name == "cpu":
            assert image[v, u] == pytest.approx(siddon_reference(level.mu_per_mm, s, p, n), rel=1e-4)


@pytest.mark.vtk_render
def test_vtk_agrees_with_cpu_on_real_ct():
    render_vtk = _vtk_renderer()
    level = real_ct_level()
    geometry = ct_geometry(level, size=96)
    pose = CarmPose(0.0, 8.0, -4.0, 2.0, 3.0, -8.0)
    cpu, vtk = render_line_integrals(level, geometry, pose), render_vtk(level, geometry, pose)
    assert np.corrcoef(cpu.ravel(), vtk.ravel())[0, 1] > 0.999
    assert np.abs(cpu - vtk).mean() < 0.01 * cpu.mean()


# ----------------------------------------------------------------------------------------------------------
# batches, caching, intensities


def _parallel_and_serial() -> tuple[np.ndarray, np.ndarray]:
    """The same three DRRs from the parallel kernel and from the serial one."""
    level = random_level(seed=5)
    geometry = CarmGeometry(CarmIntrinsics(900.0, (2.0, 2.0), (20, 16)), (0.0, 0.0, 0.0), 500.0)
    poses = np.array([[0, 0, 0, 0, 0, 0], [5, -3, 2, 4, -5, 6], [-8, 2, 6, -3, 7, -20]], float)
    limit = drr_cpu.SERIAL_WORK_LIMIT
    try:
        drr_cpu.SERIAL_WORK_LIMIT = 0
        parallel = render_line_integrals(level, geometry, poses)
        drr_cpu.SERIAL_WORK_LIMIT = 10**12
        return parallel, render_line_integrals(level, geometry, poses)
    finally:
        drr_cpu.SERIAL_WORK_LIMIT = limit


def test_parallel_and_serial_kernels_agree():
    """In a process of its own with two numba threads: ``scripts/test.sh`` runs the suite on one thread per
    worker, where the parallel kernel would run its rows one after another."""
    child = ("import sys, numba, numpy as np; sys.path.insert(0, sys.argv[1]); import test_drr as t; "
             "parallel, serial = t._parallel_and_serial(); "
             "assert numba.get_num_threads() == 2, numba.get_num_threads(); "
             "assert parallel.any() and np.array_equal(parallel, serial); print('agree')")
    env = {**os.environ, "NUMBA_NUM_THREADS": "2"}
    run = subprocess.run([sys.executable, "-c", child, str(Path(__file__).parent)], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0 and run.stdout.strip() == "agree", run.stderr[-2000:]


@pytest.mark.parametrize("serial_limit", [0, 10**12], ids=["parallel", "serial"])
def test_rendering_only_a_region_traces_exactly_its_pixels(serial_limit, monkeypatch):
    monkeypatch.setattr(drr_cpu, "SERIAL_WORK_LIMIT", serial_limit)
    level = random_level(seed=5)
    geometry = CarmGeometry(CarmIntrinsics(900.0, (2.0, 2.0), (20, 16)), (0.0, 0.0, 0.0), 500.0)
    poses = np.array([[0, 0, 0, 0, 0, 0], [5, -3, 2, 4, -5, 6]], float)
    v, u = np.mgrid[0:16, 0:20]
    field = (u - 9.5) ** 2 + (v - 7.5) ** 2 < 6.0 ** 2          # a circular exposed field
    spans = drr_cpu.row_spans(field, margin_px=1)
    grown = np.zeros_like(field)
    for row, (lo, hi) in enumerate(spans):
        grown[row, lo:hi] = True
    assert np.all(grown[field]) and not grown[0].any() and spans[0].tolist() == [0, 0]
    assert grown[1].any() and grown.sum() < field.size  # grown by one row and column, still a region
    full = render_line_integrals(level, geometry, poses)
    part = render_line_integrals(level, geometry, poses, spans=spans)
    assert np.array_equal(part[:, grown], full[:, grown]) and not part[:, ~grown].any()


@pytest.mark.parametrize("name", ENGINES)
def test_batch_equals_loop(name):
    render = engine(name)
    level = random_level(seed=3)
    intr = CarmIntrinsics(900.0, (2.0, 2.0), (20, 16))
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 500.0)
    poses = np.array([[0, 0, 0, 0, 0, 0], [5, -3, 2, 4, -5, 6], [-8, 2, 6, -3, 7, -20], [0, 9, -9, 0, 0, 90]],
                     float)
    batch = render(level, geometry, poses)
    assert batch.shape == (4, 16, 20) and batch.dtype == np.float32
    for i, pose in enumerate(poses):
        single = render(level, geometry, CarmPose.from_array(pose))
        assert single.shape == (16, 20)
        assert np.allclose(batch[i], single, rtol=1e-6, atol=1e-7)


def test_intrinsics_override_and_empty_views():
    level = random_level(seed=4)
    intr = CarmIntrinsics(900.0, (1.0, 1.0), (40, 32))
    geometry = CarmGeometry(intr, (0.0, 0.0, 0.0), 500.0)
    coarse = render_line_integrals(level, geometry, CarmPose(), intr.binned(4))
    assert coarse.shape == (8, 10)
    fine = render_line_integrals(level, geometry, CarmPose())
    # the binned pixel centre is the mean position of the 4x4 fine pixels it covers; compare smooth means
    assert coarse.mean() == pytest.approx(fine.mean(), rel=0.1)
    away = render_line_integrals(level, geometry, CarmPose(0.0, 500.0, 0.0))  # C-arm moved 0.5 m to the left
    assert not away.any()


def test_transposed_copy_is_cached_and_skipped_when_not_needed():
    mu = np.zeros((4, 5, 6), np.float32)
    assert transposed_mu(mu, (0, 1, 2)) is mu
    copy = transposed_mu(mu, (2, 0, 1))
    assert copy.shape == (6, 4, 5) and copy.flags.c_contiguous
    assert transposed_mu(mu, (2, 0, 1)) is copy
    key = (id(mu), (2, 0, 1))
    assert key in drr_cpu._layout_cache
    del mu
    assert key not in drr_cpu._layout_cache  # the copy goes with its source


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_transposed_copy_holds_the_same_numbers_as_numpys(dtype):
    """Every axis order, from a C-ordered volume and from a strided view of one, float64 cast as numpy casts it."""
    rng = np.random.default_rng(3)
    volume = rng.normal(0.02, 0.01, (9, 7, 5)).astype(dtype)
    for mu in (volume, volume[::2, 1:, ::-1]):
        for perm in [(0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]:
            expected = np.ascontiguousarray(np.transpose(mu, perm), dtype=np.float32)
            copy = transposed_mu(mu, perm)
            assert copy.dtype == np.float32 and copy.flags.c_contiguous
            assert np.array_equal(copy, expected)
        drr_cpu.clear_layout_cache()


def test_intensity_is_beer_lambert():
    line = np.array([[0.0, 1.0], [2.0, 5.0]], np.float32)
    assert np.allclose(intensity_from_line_integral(line, i0=3.0), 3.0 * np.exp(-line))


def test_vtk_without_opengl_gives_an_actionable_error():
    """With no display and no usable EGL/OSMesa the VTK engine raises a CarmRegError instead of crashing."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the glvnd override used to hide EGL is Linux-only")
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    env["__EGL_VENDOR_LIBRARY_FILENAMES"] = "/nonexistent/egl_vendor.json"
    code = ("from carmreg.logic.drr.vtk_raycast import _new_render_window\n"
            "try:\n    _new_render_window()\n"
            "except Exception as exc:\n    print(type(exc).__name__, exc)\n"
            "else:\n    print('RENDERED')\n")
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    if "RENDERED" in done.stdout:
        pytest.skip("an OpenGL context was still available (OSMesa, or EGL without glvnd)")
    assert done.returncode == 0, done.stderr[-500:]
    assert done.stdout.startswith("RegistrationError") and "CPU DRR engine" in done.stdout
