"""Stage-level tests of the registration on synthetic geometry (no image data needed)."""

import numpy as np
import pytest

from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics, project
from carmreg.logic.geometry.projection_distance import mpde_mm
from carmreg.logic.registration.depth import depth_search
from carmreg.logic.registration.fine import FineParameters, fine_search
from carmreg.logic.similarity.metrics import METRICS, prepare, similarity

# A thoracolumbar spine: 7 centroids along z, slightly kyphotic, about 28 mm apart (LPS mm).
SPINE_LPS_MM = np.array([[2.0 * np.sin(k / 3), 40 + 0.3 * (k - 3) ** 2, 85 - 28.0 * k] for k in range(7)])
GEOMETRY = CarmGeometry(CarmIntrinsics(1000.0, (0.3, 0.3), (768, 768)), (0.0, 40.0, 0.0), 600.0)


def _clicks(pose, idx=(2, 3, 4), noise_px=0.0, seed=0):
    uv = project(GEOMETRY.projection_matrix(np.asarray(pose, float)), SPINE_LPS_MM[list(idx)])
    return uv + np.random.default_rng(seed).normal(0.0, noise_px, uv.shape)


def _blob_image(shift=(0, 0), size=48):
    rr, cc = np.mgrid[:size, :size].astype(float)
    img = np.zeros((size, size))
    for r0, c0, s in ((14, 20, 3.0), (30, 26, 4.0), (22, 36, 2.5), (38, 12, 3.5)):
        img += np.exp(-((rr - r0 - shift[0]) ** 2 + (cc - c0 - shift[1]) ** 2) / (2 * s * s))
    return img


@pytest.mark.parametrize("metric", METRICS)
def test_every_metric_prefers_the_aligned_image(metric):
    fixed = _blob_image()
    rng = np.random.default_rng(3)
    fixed_noisy = 2.0 * fixed + 0.5 + rng.normal(0, 0.02, fixed.shape)  # other units, noise
    moving = np.stack([_blob_image((dy, dx)) for dy, dx in ((0, 0), (3, 0), (0, -4), (5, 5))])
    scores = similarity(metric, fixed_noisy, moving)
    assert np.argmax(scores) == 0
    assert scores[0] > scores[1:].max() + 1e-6


def test_metrics_ignore_pixels_outside_the_mask():
    fixed = _blob_image()
    moving = np.stack([_blob_image(), _blob_image()])
    moving[1, :, :8] += 50.0  # garbage in a region outside the mask
    mask = np.ones(fixed.shape, bool)
    mask[:, :10] = False
    for metric in METRICS:
        s = similarity(metric, fixed, moving, mask)
        assert s[0] == pytest.approx(s[1], rel=1e-5, abs=1e-6), metric


def test_gc_is_the_mean_correlation_of_the_two_derivative_images_inside_the_eroded_mask():
    """GC by its definition (np.corrcoef of central differences at pixels whose 3x3 neighbourhood is in the
    mask), the same from the prepared form, and exactly negated for the inverted image."""
    rng = np.random.default_rng(5)
    fixed, moving = _blob_image() + rng.normal(0, 0.05, (48, 48)), np.stack([_blob_image((2, 1)), _blob_image()])
    mask = np.zeros(fixed.shape, bool)
    mask[4:40, 6:45] = True
    inner = np.zeros_like(mask)
    inner[5:39, 7:44] = True

    def derivatives(img):
        du, dv = np.zeros_like(img), np.zeros_like(img)
        du[:, 1:-1], dv[1:-1, :] = img[:, 2:] - img[:, :-2], img[2:, :] - img[:-2, :]
        return du[inner], dv[inner]

    fu, fv = derivatives(fixed)
    expected = [0.5 * (np.corrcoef(fu, mu)[0, 1] + np.corrcoef(fv, mv)[0, 1]) for mu, mv in map(derivatives, moving)]
    scores = similarity("gc", fixed, moving, mask, dtype=np.float64)
    assert scores == pytest.approx(expected, abs=1e-12)
    assert prepare("gc", fixed, mask, dtype=np.float64)(moving) == pytest.approx(expected, abs=1e-12)
    assert similarity("gc", fixed, 3.0 - 2.0 * moving, mask, dtype=np.float64) == pytest.approx(-scores, abs=1e-12)


def test_compiled_gc_repeats_numpy_form_and_reads_float32_as_its_float64_copy():
    """``gc_kernel`` (the prepared GC's moving half) gives the numpy form's numbers (centred derivatives, norms, a
    product) to rounding, the same scores for a float32 stack and its float64 copy, the same on the calling thread
    and in parallel, and 0 along an axis whose derivatives are constant."""
    from carmreg.logic.similarity import gc_kernel
    from carmreg.logic.similarity.metrics import GradientCorrelation

    rng = np.random.default_rng(2)
    stack = rng.normal(size=(5, 37, 41)).astype(np.float32)
    yy, xx = np.mgrid[:37, :41]
    field = (yy - 18) ** 2 + (xx - 20) ** 2 < 17 ** 2
    gc = GradientCorrelation(stack[0].astype(np.float64), field)
    flat, i = stack.reshape(5, -1).astype(np.float64), gc.index
    expected = []
    for du, dv in zip(flat[:, i + 1] - flat[:, i - 1], flat[:, i + 41] - flat[:, i - 41], strict=True):
        du, dv = du - du.mean(), dv - dv.mean()
        expected.append(0.5 * (du @ gc.fixed_u / np.linalg.norm(du) + dv @ gc.fixed_v / np.linalg.norm(dv)))
    scores = gc(stack)
    assert scores == pytest.approx(expected, abs=1e-13) and scores[0] == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_array_equal(scores, gc(stack.astype(np.float64)))
    fixed_u, fixed_v = gc.fixed_u[None], gc.fixed_v[None]
    in_parallel = np.zeros((5, 1))
    gc_kernel._parallel(stack.reshape(5, -1), i, 41, fixed_u, fixed_v, in_parallel)
    np.testing.assert_array_equal(in_parallel[:, 0], scores)
    ramp = np.broadcast_to(np.arange(41, dtype=np.float32), (37, 41))  # du constant, dv zero: nothing to correlate
    assert gc(ramp[None]).tolist() == [0.0]


def test_several_gc_maps_in_one_pass_are_each_map_bit_for_bit():
    """``gc_maps`` (the polarity and storage maps over the DRR database in one pass) gives exactly what
    ``similarity`` gives map by map, over several chunks, in float32 and float64; an empty field scores 0."""
    from carmreg.logic.similarity.metrics import gc_maps

    rng = np.random.default_rng(8)
    moving = rng.normal(size=(23, 30, 28)).astype(np.float32)
    fixed = [rng.normal(size=(30, 28)) for _ in range(3)]
    field = np.zeros((30, 28), bool)
    field[2:27, 3:25] = True
    for dtype in (np.float32, np.float64):
        shared = gc_maps(fixed, moving, field, dtype=dtype)
        for f, scores in zip(fixed, shared, strict=True):
            np.testing.assert_array_equal(scores, similarity("gc", f, moving, field, chunk=10, dtype=dtype))
        assert shared[0].dtype == np.float64 and np.ptp(shared[0]) > 0.1
    empty = gc_maps(fixed, moving, np.zeros((30, 28), bool))
    assert [s.tolist() for s in empty] == [[0.0] * 23] * 3


def test_depth_search_recovers_magnification_from_intervertebral_distances():
    true_pose = [35.0, 4.0, -6.0, 0, 0, 0]
    result = depth_search(GEOMETRY, 4.0, -6.0, SPINE_LPS_MM[2:5], _clicks(true_pose))
    assert result.tx_mm == pytest.approx(35.0, abs=0.5)
    assert result.magnification == pytest.approx(1000.0 / (600.0 - 35.0 - 0.0), rel=0.02)
    assert result.cost_mm < 0.05
    # the scan starts far and walks toward the patient in 10 mm steps
    assert np.all(np.diff(result.tx_scan_mm) == pytest.approx(10.0))


def test_fine_search_converges_on_exact_clicks_and_repeats_bit_for_bit():
    true_pose = np.array([20.0, 3.0, -5.0, 1.0, 0.0, 0.0])
    uv = _clicks(true_pose, idx=(1, 2, 3, 4, 5))
    start = true_pose + [15.0, 4.0, -3.0, -1.0, 0, 0]
    params = FineParameters(rotation_weight_mm_per_deg2=0.0, seed=7)
    a = fine_search(GEOMETRY, start, SPINE_LPS_MM[1:6], uv, params)
    b = fine_search(GEOMETRY, start, SPINE_LPS_MM[1:6], uv, params)
    assert a.mpde_mm < 0.05
    assert np.array_equal(a.pose, b.pose)
    assert a.evaluations <= 2000 + params.popsize
    assert a.convergence[-1][1] <= a.convergence[0][1]


def test_fine_search_holds_a_pinned_parameter_and_fits_the_others():
    """``pinned=(0,)``: the source depth stays where it starts, the other five parameters fit the clicks; at the
    true depth that is the true pose, 60 mm off it the clicks are fitted worse (the depth is not free)."""
    true_pose = np.array([20.0, 3.0, -5.0, 1.0, 0.0, 0.0])
    uv = _clicks(true_pose, idx=(1, 2, 3, 4, 5))
    params = FineParameters(rotation_weight_mm_per_deg2=0.0, seed=7)
    start = true_pose + [0.0, 4.0, -3.0, -1.0, 0, 0]
    at_true = fine_search(GEOMETRY, start, SPINE_LPS_MM[1:6], uv, params, pinned=(0,))
    assert at_true.pose[0] == 20.0 and at_true.mpde_mm < 0.05
    assert np.abs(at_true.pose - true_pose).max() < 0.5
    assert all(p[0] == 20.0 for _, p in at_true.trajectory)
    off = fine_search(GEOMETRY, start + [60.0, 0, 0, 0, 0, 0], SPINE_LPS_MM[1:6], uv, params, pinned=(0,))
    assert off.pose[0] == 80.0 and off.mpde_mm > 0.5


def test_fine_stage_is_anchored_against_the_three_point_degeneracy():
    """Three nearly collinear clicks: the unanchored fit drives mPDE to ~0 with a wrong rotation and sends
    the other levels away; the anchored default keeps them close."""
    true_pose = np.array([25.0, 2.0, 0.0, 0.0, 0.0, 0.0])
    clicked = (2, 3, 4)
    others = [0, 1, 5, 6]
    uv = _clicks(true_pose, clicked, noise_px=4.0, seed=11)  # ~1.2 mm click noise
    start = true_pose + [12.0, 3.0, 2.0, 0, 0, 0]
    P_true = GEOMETRY.projection_matrix(true_pose)

    def unfitted_error(pose):
        P = GEOMETRY.projection_matrix(pose)
        d = project(P, SPINE_LPS_MM[others]) - project(P_true, SPINE_LPS_MM[others])
        return np.linalg.norm(d * 0.3, axis=1).max()

    free = FineParameters(rotation_weight_mm_per_deg2=0.0, bounds=(200, 200, 200, 90, 90, 90),
                          sigma=(10, 3, 3, 20, 20, 20), seed=3)
    unanchored = fine_search(GEOMETRY, start, SPINE_LPS_MM[list(clicked)], uv, free)
    anchored = fine_search(GEOMETRY, start, SPINE_LPS_MM[list(clicked)], uv, FineParameters(seed=3))
    assert unanchored.mpde_mm < anchored.mpde_mm            # the free fit "wins" on the fitted points...
    assert unfitted_error(anchored.pose) < 5.0               # ...but only the anchored one is right elsewhere
    assert unfitted_error(unanchored.pose) > 1.4 * unfitted_error(anchored.pose)
    assert np.abs(unanchored.pose[3:]).max() > 10.0         # the free fit swung the C-arm round
    assert np.abs(anchored.pose[3:]).max() < 3.0             # the anchored one stayed near AP


def test_mpde_is_in_detector_millimetres():
    pose = np.zeros(6)
    uv = _clicks(pose) + np.array([10.0, 0.0])  # 10 px = 3 mm at 0.3 mm pixels
    assert mpde_mm(GEOMETRY, pose, SPINE_LPS_MM[2:5], uv) == pytest.approx(3.0, rel=1e-9)


def test_depth_stage_recentres_the_translation_the_coarse_grid_left():
    true_pose = np.array([-20.0, 6.0, 12.0, 0, 0, 0])
    uv = _clicks(true_pose)
    start_mpde = mpde_mm(GEOMETRY, np.array([-20.0, 0.0, 16.0, 0, 0, 0]), SPINE_LPS_MM[2:5], uv)
    result = depth_search(GEOMETRY, 0.0, 16.0, SPINE_LPS_MM[2:5], uv)
    pose = np.array([result.tx_mm, result.ty_mm, result.tz_mm, 0, 0, 0])
    assert start_mpde > 4.0
    assert mpde_mm(GEOMETRY, pose, SPINE_LPS_MM[2:5], uv) < 0.05
    assert (result.ty_mm, result.tz_mm) == (pytest.approx(6.0, abs=0.2), pytest.approx(12.0, abs=0.2))
