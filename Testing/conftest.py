"""Shared pytest fixtures: where the optional real data live, and small synthetic volumes.

Real data are optional: tests that need them skip cleanly when they are absent, so the suite runs from a
bare checkout. ``../shared`` (beside the repository) holds the TotalSegmentator test CTs; the product
itself never needs it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = REPO_ROOT.parent / "shared"


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def shared_data_dir() -> Path:
    """``../shared/data``; skips the test when it is absent."""
    path = SHARED_DIR / "data"
    if not path.is_dir():
        pytest.skip(f"shared data folder {path} is absent")
    return path


@pytest.fixture(scope="session")
def totalseg_dir(shared_data_dir: Path) -> Path:
    """The TotalSegmentator test CTs (NIfTI); skips when absent."""
    path = shared_data_dir / "totalsegmentator-tests"
    if not (path / "example_ct_sm.nii.gz").is_file():
        pytest.skip(f"TotalSegmentator test CTs are absent from {path}")
    return path


@pytest.fixture(scope="session")
def drr_cache_dir(tmp_path_factory, request) -> str:
    """One DRR database cache folder for the whole session, shared by the pytest-xdist workers. A database is keyed
    on the CT's mu level, the nominal geometry and the grid (``registration.database.database_key``), so
    registrations of the same CT on the same detector share one, whichever test (on whichever worker) builds it
    first; the same numbers as a fresh build (float32 saved whole, written atomically, so two workers building the
    same one at once only cost the time). Tests of the cache itself (damage, keys, unwritable folders) use folders
    of their own."""
    if not hasattr(request.config, "workerinput"):  # not an xdist worker
        return str(tmp_path_factory.mktemp("drr-cache"))
    shared = tmp_path_factory.getbasetemp().parent / "drr-cache-shared"  # the run's folder above the workers'
    shared.mkdir(exist_ok=True)
    return str(shared)


@pytest.fixture(scope="session")
def sample_case_dir() -> Path:
    """``Resources/SampleCase``; skips when its CT (ct.nrrd) has not been generated."""
    path = REPO_ROOT / "Resources" / "SampleCase"
    if not (path / "ct.nrrd").is_file():
        pytest.skip("Resources/SampleCase/ct.nrrd is absent (run the sample-case script)")
    return path


@pytest.fixture(scope="session")
def sample_ct(sample_case_dir: Path):
    """The sample case's CT (Volume), vertebra label map (uint8 array) and CT centroids (Landmarks3D)."""
    import numpy as np

    from carmreg.logic.io.landmarks import read_landmarks_3d
    from carmreg.logic.io.volumes import load_volume

    ct = load_volume(sample_case_dir / "ct.nrrd")
    labels = np.asarray(load_volume(sample_case_dir / "vertebrae.nrrd").hu).astype(np.uint8)
    return ct, labels, read_landmarks_3d(sample_case_dir / "ct_centroids.mrk.json")


@pytest.fixture(scope="session")
def small_real_ct(totalseg_dir: Path):
    """A small real CT (122 x 101 x 30 voxels at 3 mm, int16 HU) as a Volume; skips when absent."""
    from carmreg.logic.io.volumes import load_volume

    return load_volume(totalseg_dir / "example_ct_sm.nii.gz")


def oblique_affine(spacing_mm=(0.7, 0.8, 2.0), angles_deg=(20.0, -15.0, 30.0),
                   origin_lps_mm=(-101.25, 37.5, 812.125)) -> np.ndarray:
    """A 4x4 ijk -> LPS with rotated (oblique) orthonormal directions and anisotropic spacing."""
    from scipy.spatial.transform import Rotation

    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix() * np.asarray(
        spacing_mm)[None, :]
    affine[:3, 3] = origin_lps_mm
    return affine


@pytest.fixture
def oblique_volume():
    """A 24 x 20 x 9 int16 volume with an oblique affine and distinct values (-1000 .. ~3000 HU)."""
    from carmreg.logic.geometry.volume import Volume

    rng = np.random.default_rng(7)
    hu = rng.integers(-1000, 3000, size=(24, 20, 9)).astype(np.int16)
    return Volume(hu, oblique_affine(), "synthetic-oblique")


@pytest.fixture(scope="session")
def tiny_db_inputs():
    """A 16^3 CT of air with a bone bar (4 mm voxels) and a 12 x 12 px detector: the inputs of a DRR database
    small enough to build in milliseconds (mu level, geometry, intrinsics, ty grid, tz grid)."""
    from carmreg.logic.geometry.camera import CarmGeometry, CarmIntrinsics
    from carmreg.logic.geometry.volume import MuPyramid, Volume
    from carmreg.logic.registration.database import grid

    hu = np.full((16, 16, 16), -1000, np.int16)
    hu[6:10, 6:10, 4:12] = 1000
    volume = Volume(hu, np.diag([4.0, 4.0, 4.0, 1.0]), "tiny")
    intrinsics = CarmIntrinsics(1000.0, (4.0, 4.0), (12, 12))
    geometry = CarmGeometry(intrinsics, tuple(volume.center_lps_mm()), 600.0)
    return MuPyramid(volume).level(None), geometry, intrinsics, grid(4.0, 2.0), grid(2.0, 2.0)


@pytest.fixture
def click_spacing_order():
    """The test's registrations take unnamed clicks' labellings in the order before stop 65
    (``appearance_cases.ordered_by_click_spacing``: tests that pin what the checks do on wrong leaders)."""
    from appearance_cases import ordered_by_click_spacing

    with ordered_by_click_spacing():
        yield
