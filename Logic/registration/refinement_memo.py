"""Image refinements already run in one registration, by everything they depend on.

A labelling's image refinement (``image_refine.intensity_refine`` from ``labelling_fit``) is a seeded search: the
same inputs give the same result, bit for bit. One registration asks for some of them twice - the check on the
mirrored image (spatial stage) and the orientation judged again with the levels' winner register the same
labellings on the same mirrored image; a second search round of the leading two refits them from the same tilted
poses and restarts them from the same poses when the first round left them where they were. ``RefinementMemo``
answers such a repeat with the result it had instead of running it again.

What a refinement depends on, its key:

- the mu level's volume, the X-ray image it compares with and its exposed field: their contents, a 16-byte BLAKE2b
  digest of the bytes with shape and dtype, computed once per array object (the mirrored image is made anew each
  time it is asked for; arrays are never changed in place here, as ``drr.cpu``'s layout cache assumes too);
- the level's affine, the geometry and the refinement's parameters (values);
- the labelling's CT points and clicks, and the start pose (their float64 bytes);
- its stopping rules: ``early_stop.GiveUpAbove`` and ``early_stop.Rejoins`` are values (the bar; the
  labelling's pose and score the refit may rejoin). A refinement with any other stopping rule is not remembered.
  One whose rules never stopped it ran as it would have without them (they only end the search), so it also
  answers the same refinement asked without stopping rules; one a rule stopped is kept resumable
  (``RefineResult.resume``), and asked for without rules (``labelling_fit.complete``, a display judged again in
  full) it is run on from where it stopped instead of from its start: the same search, bit for bit.

Nothing else enters ``intensity_refine`` but its cancel check, which only raises. Each answer is a copy of the
result as it was first returned (``RefineResult`` is later annotated in place: ``agreement`` sets
``equalised_similarity``), so a remembered result is what a fresh run would have returned; a cancelled refinement
returns nothing and is not remembered.
"""

from __future__ import annotations

import dataclasses
import hashlib
import weakref
from collections.abc import Callable

import numpy as np

from carmreg.logic.registration.early_stop import GiveUpAbove, Rejoins
from carmreg.logic.registration.image_refine import RefineResult

_STOPPING_RULES = (GiveUpAbove, Rejoins)


def _copy(result: RefineResult) -> RefineResult:
    """``result`` with its own pose and convergence record, not resumable (only the memo resumes a search)."""
    return dataclasses.replace(result, pose=np.array(result.pose, float), convergence=list(result.convergence),
                               resume=None)


def _values(x) -> tuple:
    """A float64 array's shape and bytes: equal exactly when the numbers are."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    return a.shape, a.tobytes()


class RefinementMemo:
    """The refinements one registration has run (module docstring); ``result`` runs or recalls one."""

    def __init__(self):
        self.run = 0                                      # refinements run through it
        self.recalled = 0                                 # ... answered from memory
        self.resumed = 0                                  # ... run on from where a stopping rule had ended them
        self._stopped: dict[tuple, RefineResult] = {}     # stopped early, resumable, by their key without rules
        self._results: dict[tuple, RefineResult] = {}
        self._digests: dict[int, tuple[weakref.ref, tuple]] = {}  # id(array) -> (the array, weakly; its digest)

    def _digest(self, image: np.ndarray) -> tuple:
        """(shape, dtype, 16-byte BLAKE2b of the bytes) of ``image``, computed once per live array object."""
        hit = self._digests.get(id(image))
        if hit is not None and hit[0]() is image:
            return hit[1]
        a = np.ascontiguousarray(image)
        digest = a.shape, str(a.dtype), hashlib.blake2b(a.view(np.uint8).ravel(), digest_size=16).digest()
        self._digests[id(image)] = (weakref.ref(image), digest)
        return digest

    def key(self, mu, geometry, start_pose: np.ndarray, image: np.ndarray, mask: np.ndarray,
            points_lps_mm: np.ndarray, uv_px: np.ndarray, params, give_up=None, rejoined=None) -> tuple | None:
        """What a refinement with these inputs depends on (module docstring), given as to
        ``image_refine.intensity_refine``; None when a stopping rule is not a value (it is then not remembered)."""
        if any(rule is not None and not isinstance(rule, _STOPPING_RULES) for rule in (give_up, rejoined)):
            return None
        return (self._digest(mu.mu_per_mm), _values(mu.ijk_to_lps), geometry, self._digest(image), self._digest(mask),
                dataclasses.astuple(params), _values(points_lps_mm), _values(uv_px), _values(start_pose), give_up,
                rejoined)

    def result(self, key: tuple | None, run: Callable[[], RefineResult]) -> RefineResult:
        """The refinement of ``key``: recalled when it ran before (a copy of the one kept), else ``run()``'s result,
        a copy of it kept unless ``key`` is None; the caller's result is always its own."""
        known = self._results.get(key) if key is not None else None
        if known is not None:
            self.recalled += 1
            return _copy(known)
        stopped = self._stopped.pop(key, None) if key is not None else None
        if stopped is not None:  # the same search, stopped early before: run on from there
            self.resumed += 1
            result = stopped.resume()
        else:
            result = run()
            self.run += 1
        if key is not None:
            self._results[key] = _copy(result)
            plain = key[:-2] + (None, None)   # the same refinement without stopping rules
            if result.resume is not None:
                self._stopped.setdefault(plain, result)
            elif plain != key:  # no rule stopped it: it ran as it would have without them
                self._results.setdefault(plain, _copy(result))
        return result

    def as_dict(self) -> dict:
        """result.json ``stages[levels].refinements``: the labellings' image refinements of the registration so far,
        run, recalled and resumed."""
        return {"run": self.run, "recalled": self.recalled, "resumed": self.resumed}
