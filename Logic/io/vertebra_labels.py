"""A vertebra label map on the CT grid, read as CarmReg values (1 + ``LEVEL_NAMES.index``).
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.errors import GeometryError
from carmreg.logic.geometry.vertebrae import CARMREG_VERTEBRAE
from carmreg.logic.geometry.volume import Volume


def load_vertebra_labels(path, ct: Volume) -> np.ndarray:
    """A vertebra label map on the CT grid, as CarmReg values. TotalSegmentator v2 maps (values above 27)
    are relabelled; anything else is taken as CarmReg values (1 + LEVEL_NAMES.index)."""
    from carmreg.logic.geometry.vertebrae import TOTALSEGMENTATOR_V2_VERTEBRAE, to_carmreg_labels
    from carmreg.logic.io.volumes import load_volume

    labels = load_volume(path)
    if labels.shape != ct.shape or not np.allclose(labels.ijk_to_lps, ct.ijk_to_lps, atol=1e-3):
        raise GeometryError(f"{path}: the vertebra label map ({'x'.join(map(str, labels.shape))}) is not on the "
                            f"CT grid ({'x'.join(map(str, ct.shape))}); resample it onto the CT first")
    values = np.asarray(labels.hu)
    if int(values.max()) > max(CARMREG_VERTEBRAE):
        return to_carmreg_labels(values, TOTALSEGMENTATOR_V2_VERTEBRAE)
    return values.astype(np.uint8)
