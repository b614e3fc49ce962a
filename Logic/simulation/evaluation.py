"""Score a registration against a known truth (simulated cases), on the levels the fit did not use.

For every CT-labelled level k visible in the image (its true image position inside the exposed detector):
- ``pde_pose_mm``: | P_found X_k - P_true X_k | on the detector (mm): the pose error seen at that level;
- ``pde_image_mm``: | shown(P_found X_k) - uv_true_k | (mm), uv_true_k = where the vertebra really appears (after
  per-level motion and distortion), ``shown`` the found detector's distortion (``geometry.distortion``:
  where the result draws the level; none on a pinhole): what a surgeon would see;
- ``named_correctly``: shown(P_found X_k) is closer to uv_true_k than to any other level's true position, i.e. the
  label drawn on the overlay sits on the right vertebra.
The field's thresholds: success < 5 mm, gross failure > 20 mm (on the detector).
"""

from __future__ import annotations

import numpy as np

from carmreg.logic.geometry.camera import project


def evaluate(projection_matrix: np.ndarray, centroids: dict, truth: dict, fitted: set[str], shown=None) -> dict:
    """Per-level scores and summaries. ``truth`` as in ground_truth.json (projection_matrix, levels); ``shown``:
    ideal (pinhole) pixel positions (n, 2) -> where the found detector shows them (``RadialDistortion.distort``;
    None: a pinhole)."""
    P_true = np.asarray(truth["projection_matrix"], float)
    spacing = np.asarray(truth["intrinsics"]["pixel_spacing_mm"], float)
    true_uv = {lb: np.asarray(v["uv_true_px"], float) for lb, v in truth["levels"].items()
               if v.get("visible", True) and lb in centroids}
    rows = []
    for label, uv_t in true_uv.items():
        x = np.asarray(centroids[label], float)[None]
        uv_found = project(projection_matrix, x)[0]
        uv_pose = project(P_true, x)[0]
        uv_drawn = uv_found if shown is None else shown(uv_found[None])[0]
        others = [np.linalg.norm((uv_drawn - v) * spacing) for lb, v in true_uv.items() if lb != label]
        own = float(np.linalg.norm((uv_drawn - uv_t) * spacing))
        rows.append({"label": label, "fitted": label in fitted,
                     "pde_pose_mm": float(np.linalg.norm((uv_found - uv_pose) * spacing)),
                     "pde_image_mm": own, "named_correctly": bool(not others or own < min(others))})
    unfitted = [r for r in rows if not r["fitted"]]
    return {"levels": rows,
            "all_named_correctly": all(r["named_correctly"] for r in rows),
            "unfitted_pde_pose_mm": [r["pde_pose_mm"] for r in unfitted],
            "unfitted_pde_image_mm": [r["pde_image_mm"] for r in unfitted],
            "max_unfitted_pde_pose_mm": max((r["pde_pose_mm"] for r in unfitted), default=0.0),
            "median_unfitted_pde_pose_mm": float(np.median([r["pde_pose_mm"] for r in unfitted]))
            if unfitted else 0.0}
