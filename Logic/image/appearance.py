"""How a stored X-ray shows the anatomy - polarity (bone dark or bone bright) and storage - found from the image
against the CT's DRRs, never assumed from the file type.

Polarity
--------
The stored values S relate to the attenuation line integral L (bone bright, what a DRR is) through an unknown
monotone map: decreasing when bone is displayed dark (fluoroscopy: S ~ I0 exp(-L) or a display of it),
increasing when bone is displayed bright (a radiograph or PACS export: S ~ a + b L, log-like). Ranking S inside
the exposed field, ``R = rank(S) / (n - 1)``, removes every increasing storage map (linear, log, gamma, 8-bit
quantisation) and keeps only its direction. With the coarse DRRs D_k of the database and gradient correlation
(GC, odd in its first argument: GC(-R, D) = -GC(R, D) exactly), one pass gives both polarities::

    g_k = GC(R, D_k);   score(bone-bright) = max_k g_k;   score(bone-dark) = max_k (-g_k)
    clarity = |score(bone-dark) - score(bone-bright)|

The larger score decides. The database's poses (no rotation, one depth) are coarse, and on a CT whose DRRs carry
features of their own a wrong-sign correlation at a wrong pose can win clearly (the appearance benchmark's second
CT: every intensifier image inverted). So the scores measured at better poses replace them (``decide_polarity``
with ``refined=``, recorded as the evidence, ``decided_by`` naming where):

- **with clicks** (``REFINED_AT_CLICKS``, ``registration.click_polarity``): the leading labellings registered
  under both polarities where the clicks put the CT; score = the best refined GC. The polarity whose best
  registration keeps the clicks fitted - within the level confidence rule's cap and not clearly worse than the
  same labelling under the other polarity - is preferred (a wrong polarity can buy GC by pulling the CT off the
  clicks: seen, 0.34 GC at 3.9 mm against 0.21 at 0.5 mm), then the higher GC (``verdict_at_clicks``). Only a
  registration that agrees with the image at all (GC >= ``FITTED_MIN_GC``) counts as keeping the clicks fitted:
  the clicks hold a registration on them whatever the image says, and a GC about 0 or negative says the image does
  not match the DRR there or matches the *inverted* one, evidence for the other polarity (seen: the independent
  cases' case 16 bone dark, bone dark GC 0.39 just off the clicks (4.2 mm) against bone bright -0.06 on them;
  the appearance benchmark's report case 9, a linear flat panel with its names given, bone dark 0.816 at 5.7 mm
  against bone bright 0.002 at 1.9 mm, the file's stated polarity then overruled; every such run with the truth
  the other polarity). Clear
  when it leads by ``CLEAR_CLICKS_GC``, reaches ``MIN_CLICKS_GC`` and keeps the clicks fitted. The two GC
  thresholds were chosen on the tune half of the appearance benchmark (first measurement: wrong verdicts led by
  at most 0.147 - all on linear flat-panel images whose field was then mis-found - and reached at most 0.27);
- **without clicks** (or too few to place the CT): each polarity's best spatial-map peaks refined on the image
  alone, the bone-dark image converted with its better storage (``REFINED_AT_DATABASE_POSES``,
  ``registration.image_polarity``); score = the best refined GC, clear at ``CLEAR_REFINED_GC``. Always, not only
  on a close call: the database's verdict was clear and wrong on the second CT's intensifier images. The refined
  verdict can be wrong too (two report cases of the second CT: every intensifier variant, the database agreeing),
  so the gap called clear was raised from 0.05 to 0.12 on the tune half: its wrong verdicts led by 0.078-0.110
  (and one large patient by 0.332), its right ones by 0.066 and more. Unclear, the leading polarity is still the
  one used, and no answer is proposed (``calibrate_noclick_polarity``).

A file that *states* its polarity (DICOM PixelIntensityRelationshipSign, ``header_explicit``) is evidence too. When
the image agrees, the polarity is clear whatever the gap. When the image disagrees, the two are in conflict: the
file's word is used (the image's verdict rests on the exposed field and the DRRs, which a collimator glow or an
unusual view can mislead - seen on a linear flat-panel image whose field was mis-found), the polarity is *not*
clear, so no level answer is confident, and the note says to check the image and the tags.

Storage
-------
Bone-dark images are converted to attenuation either as linear intensity, ``L = -log(S / S_ref)``, or as an
already log-like display, ``L = (S_ref - S) / range``. A file that states it stores the intensity itself (DICOM
PixelIntensityRelationship LIN, sign +1: ``XrayImage.stated_storage``) is converted as linear intensity, and one
whose storage the user set (``RegistrationParameters.storage``: ``--storage``, the window's and the Slicer module's
X-ray storage) as they set it (``stated_storage``); otherwise the conversion whose best DRR agrees more (max GC over
the database) is used (``dark_storage``). Both scores are recorded, and ``Appearance.storage_from`` says which rule
decided. The file's word wins because the image's is weak: on a lumbar flat-panel image stored LIN (report case 131
of the appearance benchmark, second CT) the log display agreed more, 0.52 against 0.38, and the refined agreement
then reached only 0.67 (0.86 on the same scene stored log), the contest's winner a wrong labelling kept from
confidence only by the orientation check.
Bone-bright images are attenuation-like by construction and are used linearly, ``L = (S - S_lo) / range``.

Orientation
-----------
A C-arm display can be mirrored left-right or turned (display settings), which no header records. With the
polarity's sign s, the rank image is also scored in the other orientations that keep its shape - mirrored
left-right, flipped up-down, turned 180 degrees, and on a square detector turned 90 degrees either way and the two
transposes (a quarter turn and a mirror; ``turn.ORIENTATIONS``, scored since stop 58) - against every other DRR of
the database (half the grid each way, enough to find the best)::

    score(o) = max_k s GC(o(R), D_k)

When another orientation wins by at least ``REFUSE_ORIENTATION_GC``, the image is refused for registration (the
pipeline's checks: ``ok`` false, "fix the display") and no level answer is confident. Any closer call - the stored
orientation leading by less than ``CLEAR_ORIENTATION_GC``, or another leading by less than
``REFUSE_ORIENTATION_GC`` - makes the orientation *unclear*: taken as stored, a warning, and no level answer is
confident either. A mirrored display of a near-symmetric view can win as stored by a hair (seen: a mirrored
intensifier image led as stored by 0.016 GC, with its polarity misjudged and the wrong levels one margin short of
confident), so a hair's lead is not evidence (``trusted_appearance``); and on a CT whose DRRs carry features of
their own the coarse database's orientation scores are noise (the appearance benchmark's second CT: another
orientation led correctly displayed images by up to 0.105 GC on the tune half; ``REFUSE_ORIENTATION_GC`` was
chosen above that. Applied to the recorded runs: correctly displayed second-CT images refused 0 of 108, was 69;
mirrored displays refused 9 of 9 on the chest CT and 0 of 12 on the second CT, unclear instead).

With clicks and a clear polarity, the orientation is taken again where the clicks put the CT
(``registration.click_orientation``): the labellings of the polarity check are registered on each rival
orientation of the image (those the database could not rule out, and always the left-right mirror) and the best
GC there, g(o), replaces the database scores (``Appearance.set_orientation_at_clicks``,
``orientation_decided_by``). A stored orientation the database found clearly worse than another is never made
clear by it (a conflict).
Another orientation leading the stored one by ``REFUSE_ORIENTATION_AT_CLICKS_GC`` with the clicks fitted is taken
(the image refused); the stored one leading every judged rival by ``CLEAR_ORIENTATION_AT_CLICKS_GC`` is clear;
anything between is unclear. Both were chosen on the tune half of the appearance benchmark: where the check ran
(second CT), correctly displayed images led their mirror by 0.281-0.329 GC or their mirror could not fit the clicks
at all, and the mirrored display trailed by 0.276; registered as stored and mirrored by hand (both CTs, the same
polarity, clicks fitted), correctly displayed images led by 0.213-0.498. The clear lead was lowered from 0.10 to
0.05 at stop 14, again on the tune half: a correctly displayed upper thoracic spine (T2-T4, nearly symmetric) led
its mirror by only 0.082, while every mirrored display judged at the clicks (both CTs, both halves) trailed its
mirror by 0.25 or more; over all 303 recorded clicked runs the change turns 5 tune runs (correct displays) from
ambiguous to confident or contradicted as they should be, and none of the report half.

The orientation check at the clicks needs a clear polarity, and on a mirrored display the polarity check at the clicks
finds no aligned spine under either polarity: its verdict stays unclear, sometimes for the wrong polarity (the
appearance benchmark, stop 17: 11 of 24 mirrored displays with unnamed clicks unclear, 4 of them taken bone bright). So
when the polarity at the clicks is unclear (and the user did not set it), it is judged again on the image mirrored
left-right, exactly as at the clicks (``REFINED_ON_MIRROR``, ``appearance_checks._polarity_on_displays``). That verdict
is taken only when it is clear and the mirror then leads the stored image under that polarity by
``REFUSE_ORIENTATION_AT_CLICKS_GC`` with the clicks fitted (``click_orientation.stored_against_turned``): the display is
then mirrored, the image refused, and no level answer confident. Otherwise nothing changes but the record. No threshold
of its own: the verdict's are the two at the clicks. Unnamed clicks fit an upside-down display about as well as an
upright one (they run along the spine either way), so since stop 62 the same is asked, by the same rule, of the image
flipped up-down and turned 180 degrees (``refined_on_at_clicks``) where the database could not rule that out under
either polarity (``appearance_checks._upside_down_rivals``).

A display and its polarity are found together (stop 54). A clear polarity at the clicks that only just cleared its lead
(by less than ``CHECKED_CLICKS_GC``, not confirmed by a clear second opinion without the shading; the file not stating
it, the user not setting it) on a display judged as stored can still be the wrong polarity on a mirrored display: as
stored, neither polarity shows an aligned spine, and the wrong one can lead by chance and then find the display as
stored. So the orientation is judged at the clicks under the other polarity too (``REFINED_WITH_ORIENTATION``,
``appearance_checks._orientation_under_other_polarity``: the mirror and every orientation its database scores do not
rule out, the polarity check's registrations under it). When a rival orientation there keeps the clicks fitted and leads
the stored image's GC under the polarity taken by ``REFUSE_ORIENTATION_AT_CLICKS_GC``, the image is that polarity
displayed so (``Appearance.displayed_otherwise``): refused, no level answer confident. Seen: stop 53's unseen chest
scene 353, a mirrored bone-dark intensifier PNG, names one level off: bone bright taken at the clicks by 0.115, the
display then clear as stored (0.348, the mirror 0.250 without the clicks fitted); as bone dark the mirror reaches 0.865
with the clicks fitted. No threshold of its own.

Without clicks the same holds (stop 28): a mirrored display the database did not refuse left the image-alone polarity
unclear, often for the wrong polarity (the appearance benchmark's report halves: 5 of the 7 such runs recorded at stops
21 and 27). So when the polarity found without clicks is unclear and the orientation not clearly as stored (the user did
not set the polarity), each polarity is refined on the image mirrored left-right as on the image as stored
(``REFINED_ON_MIRROR_WITHOUT_CLICKS``, ``appearance_checks._orientation_without_clicks``), and since stop 56 on the
image flipped up-down and turned 180 degrees too where the database could not rule those out
(``refined_on_without_clicks``). When the best of them, under its own leading polarity, agrees with the image by
``REFUSE_ORIENTATION_AT_CLICKS_GC`` more than the image as stored does under that polarity, the display is so shown:
that verdict is taken (clear at ``CLEAR_REFINED_GC``) and the image refused
(``Appearance.set_orientation_without_clicks``). Otherwise nothing changes but the record.

A polarity still unclear without clicks, or clear by less than ``CHECKED_REFINED_GC`` (stop 32; the image's verdict,
the file not stating a polarity), on an image taken as stored (the user did not set it), gets a second
opinion (stop 29, ``REFINED_WITHOUT_SHADING``, ``appearance_checks._polarity_without_shading``): the same
search with the X-ray, the database and every DRR compared without their shading above ``WITHOUT_SHADING_MM``
(``image.shading``). The first verdict's misses were failures of its search, not of the image (stop 28,
``Testing/Benchmarks/large_patient_shading.py``): a large patient's scatter shading outweighing the faint bone, a
view tilted out of the image plane whose plain map's peaks lay away from the true pose. When it leads with the
other polarity, its polarity is used (``Appearance.as_second_opinion``), but **never called clear**, so no level
answer is proposed on it: on the tune half (``Testing/Benchmarks/measure_without_shading.py``) it was right on
each of its 5 disagreements with the first verdict, and its wrong verdicts over all 60 tune images led by at most
0.081; but a first version that also let a clear second opinion propose levels proposed two answers one level off
on the unseen cases (a low-dose intensifier and a large patient, the polarity right): where only the image without
its shading shows the polarity, the image as it is does not name levels reliably. When it agrees with the first
verdict, nothing changes but the record.

The decision, how clear it was, the scores it rests on, what the file's header said and whether the user
overrode it are kept in ``Appearance`` (``result.json["appearance"]``). An unclear polarity or orientation, or a
user's polarity the image clearly contradicts, keeps any level answer from being confident
(``registration.level_confidence``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from carmreg.logic.image.prepare import STORAGES, attenuation, bin_image_to, bin_mask_to, rank_image
from carmreg.logic.image.turn import ORIENTATIONS
from carmreg.logic.similarity.metrics import gc_maps, similarity

POLARITIES = ("bone-dark", "bone-bright")
POLARITY_SETTINGS = ("auto", *POLARITIES)
"""What the user may set the polarity to (``RegistrationParameters.polarity``): auto, found from the image, or one."""
CLEAR_POLARITY_GC = 0.05    # GC gap of the database scores called clear (evidence when nothing was refined: a
#                             polarity set by the user is checked against the database alone)
CLEAR_REFINED_GC = 0.22     # GC gap of the refined scores (no clicks) called clear (tune half of the appearance
#                             benchmark, 110 runs (stop 28): a large patient's wrong verdict led by 0.210 on the fresh
#                             tune cases; 0.15 at stop 16 (its tune runs' wrong ones led by <= 0.141), 0.12 at stop 15)
CLEAR_CLICKS_GC = 0.10      # at the clicks' poses: the GC gap called clear (tune half of the appearance benchmark)
MIN_CLICKS_GC = 0.30        # ... and the winner's GC must reach this (ditto)
FITTED_MIN_GC = 0.10        # ... and a registration's GC before its keeping the clicks fitted counts (stop 21,
#                             replayed on the tune half's 460 recorded verdicts: 0.05-0.15 set 3-5 unclear ones
#                             right and none wrong, 0.20 broke 3; 0 until then; no clear verdict changes below 0.30)
REFINED_AT_DATABASE_POSES = "refined"            # no clicks: each polarity's spatial-map peaks refined on the image
REFINED_AT_CLICKS = "at the clicks' poses"        # registered where the clicks put the CT (click_polarity)
ON_TURNED_AT_CLICKS = f"{REFINED_AT_CLICKS}, on the image "  # ... on a turned or mirrored display


def refined_on_at_clicks(orientation: str, without_shading_mm: float = 0.0) -> str:
    """With clicks: how a polarity registered where the clicks put the CT on orientation ``orientation`` of the image
    (the clicks turned with it; compared without the shading above ``without_shading_mm`` when > 0) was measured
    (``decided_by``)."""
    shading = f", without the shading above {without_shading_mm:g} mm" if without_shading_mm > 0 else ""
    return ON_TURNED_AT_CLICKS + orientation.replace("-", " ") + shading


REFINED_ON_MIRROR = refined_on_at_clicks("mirrored-left-right")  # ... on the mirrored display


def refined_on_without_clicks(orientation: str) -> str:
    """No clicks: how a polarity refined on orientation ``orientation`` of the image was measured (``decided_by``)."""
    return f"refined, on the image {orientation.replace('-', ' ')}"


REFINED_ON_MIRROR_WITHOUT_CLICKS = refined_on_without_clicks("mirrored-left-right")  # no clicks, the mirrored display
CHECKED_REFINED_GC = 0.35   # no clicks: a clear verdict leading by less than this gets the second opinion too (the
#                             tune half's wrong no-click verdicts led by up to 0.332)
CHECKED_CLICKS_GC = CHECKED_REFINED_GC  # with clicks: the same (stop 36; no tune half has a wrong clear verdict
#                             at the clicks to set it from; tried first at 0.20, above every large patient's clear
#                             verdict on the tune halves, 0.111-0.176; the tune runs clear by 0.20-0.35 re-run at 0.35:
#                             none changed, the second opinion agreeing on all 12)
WITHOUT_SHADING_MM = 20.0   # no clicks, the second opinion: the shading removed above this scale (detector mm)
REFINED_WITHOUT_SHADING = f"refined, without the shading above {WITHOUT_SHADING_MM:g} mm"  # no clicks, unshaded
REFINED_AT_CLICKS_WITHOUT_SHADING = f"at the clicks' poses, without the shading above {WITHOUT_SHADING_MM:g} mm"
REFINED_WITH_ORIENTATION = f"{REFINED_AT_CLICKS}, with the display's orientation judged under both polarities"


def measured_at_clicks(refined_by: str) -> bool:
    """Whether scores measured ``refined_by`` were registered where the clicks put the CT (as stored, on a turned or
    mirrored display, or without the shading): their verdict is ``verdict_at_clicks``'s."""
    return refined_by in (REFINED_AT_CLICKS, REFINED_AT_CLICKS_WITHOUT_SHADING) or refined_by.startswith(
        ON_TURNED_AT_CLICKS)


CLEAR_ORIENTATION_GC = 0.03  # the stored orientation must lead every other by this much
REFUSE_ORIENTATION_GC = 0.12  # another orientation must lead the stored one by this much to be called
CLEAR_ORIENTATION_AT_CLICKS_GC = 0.05   # at the clicks' poses: the stored orientation's lead called clear
REFUSE_ORIENTATION_AT_CLICKS_GC = 0.10  # ... and another orientation's lead that refuses the image
CLOSE_ORIENTATION_AT_CLICKS_GC = 0.15   # ... a lead either way under this is judged with more labellings (tune: a
#                                         mirrored display trailed its mirror by 0.108, correct ones led by 0.052)
def database_orientation(scores: dict) -> str:
    """The database's verdict on the orientation from its ``orientation_scores``: the best one when it leads the
    stored one by ``REFUSE_ORIENTATION_GC`` (the image refused), else "as-stored" (module docstring)."""
    best = max(scores, key=scores.get)
    return best if scores[best] - scores["as-stored"] >= REFUSE_ORIENTATION_GC else "as-stored"


def displayed_rival(scores: dict, fitted: dict, against_gc: float) -> str | None:
    """The orientation an image is displayed in, judged at the clicks (``click_orientation``): of the rivals of the
    stored one (``scores``: {orientation: GC}, nan or None where the clicks could not be fitted), the best that keeps
    the clicks fitted (``fitted``), when

        g(o) - against_gc >= REFUSE_ORIENTATION_AT_CLICKS_GC

    else None. ``against_gc``: the stored image's GC at the clicks (``Appearance.set_orientation_at_clicks``), or
    under the polarity taken when ``scores`` are the other polarity's (``displayed_under_other_polarity``)."""
    rivals = [o for o, g in scores.items() if o != "as-stored" and g is not None and np.isfinite(g) and fitted[o]]
    best = max(rivals, key=scores.get, default=None)
    return best if best is not None and scores[best] - against_gc >= REFUSE_ORIENTATION_AT_CLICKS_GC else None


def trusted_appearance(clear: bool, orientation: str, orientation_clear: bool) -> bool:
    """Whether a level answer may be confident on this appearance: the polarity clear, and the image matching the
    CT best as stored by a clear lead (``CLEAR_ORIENTATION_GC`` on the database, ``CLEAR_ORIENTATION_AT_CLICKS_GC``
    at the clicks' poses). Also applied to recorded runs
    (``Testing/Benchmarks/calibrate_confidence.py``)."""
    return bool(clear and orientation == "as-stored" and orientation_clear)


STORAGE_FROM_IMAGE = "image (the conversion whose best DRR agrees more)"
STORAGE_FROM_FILE = "file (DICOM PixelIntensityRelationship LIN, sign +1: linear intensity)"
STORAGE_FROM_USER = "user (set, not found)"
STORAGE_SET_UNUSED = "user (set, unused: a bone-bright image is used as displayed)"
"""``Appearance.storage_from``: how a bone-dark image's storage was decided (``dark_storage``), or that the user's
storage went unused on a bone-bright image."""
STORAGE_NOTES = {STORAGE_FROM_FILE: " (as the file states)", STORAGE_FROM_USER: " (as set)",
                 STORAGE_SET_UNUSED: " (the storage set applies to bone-dark images only)"}
"""What ``Appearance.summary`` says after the storage, by ``storage_from`` (nothing when the image decided)."""


@dataclass
class Appearance:
    """How the X-ray shows bone, and why we think so (module docstring)."""

    polarity: str                     # "bone-dark" | "bone-bright": the one used
    storage: str                      # "linear-intensity" (-log) | "log-display" (linear)
    decided_by: str                   # "image" | "image (<refined_by>)" | "user" | "header ..."
    clear: bool                       # the evidence clearly supports ``polarity`` (or the user's choice)
    clarity_gc: float                 # GC gap between the polarities (database or refined scores; at the clicks
    #                                   the used polarity's lead, < 0 when the other gained GC off the clicks)
    threshold_gc: float               # the gap called clear
    scores: dict                      # {"database": {"bone-dark": g, "bone-bright": g}, "refined": {...} | None,
    #                                    "storage": {"linear-intensity": g, "log-display": g}}
    header_polarity: str              # what the file's header (or the format's default) says
    header_source: str
    image_polarity: str               # what the image says, whatever was used
    note: str = ""                    # in words, for the report and the GUI
    orientation: str = "as-stored"    # the orientation the image is taken to have (ORIENTATIONS; module docstring)
    orientation_scores: dict | None = None  # orientation -> best signed GC over the (halved) database
    orientation_clear: bool = True    # the stored orientation leads every other clearly (by whatever decided)
    orientation_decided_by: str = "image (database)"  # or "image (at the clicks' poses)", or on the mirror
    orientation_at_clicks: dict | None = None  # the evidence at the clicks' poses (``click_orientation``)
    orientation_without_clicks: dict | None = None  # no clicks: {orientation: refined GC} that took another one
    storage_from: str = STORAGE_FROM_IMAGE  # or the file's statement, or the user's (``stated_storage``)

    @property
    def bone_dark(self) -> bool:
        return self.polarity == "bone-dark"

    @property
    def trusted(self) -> bool:
        """A level answer may be confident (``trusted_appearance``)."""
        return trusted_appearance(self.clear, self.orientation, self.orientation_clear)

    @property
    def lent_by_display(self) -> bool:
        """The polarity in use was lent by a turned or mirrored display's clear verdict at the clicks, the display
        not taken (``leaned_on_display``: never clear)."""
        return not self.clear and ON_TURNED_AT_CLICKS in self.decided_by and self.orientation == "as-stored"

    def as_second_opinion(self, first: Appearance) -> None:
        """This verdict, found on the image without its shading (``REFINED_WITHOUT_SHADING``, or
        ``REFINED_AT_CLICKS_WITHOUT_SHADING``), used instead of ``first`` (the image as it is: unclear, or clear by
        less than ``CHECKED_REFINED_GC`` / ``CHECKED_CLICKS_GC``, leading with the other polarity). Never clear (module
        docstring)."""
        self.clear = False
        leaned = f"{'clearly ' if first.clear else ''}leaned {first.polarity} by {first.clarity_gc:.3f}"
        self.note = (f"{self.polarity}, found only from the image without its shading above {WITHOUT_SHADING_MM:g} "
                     f"mm (GC gap {self.clarity_gc:.3f} there; as it is, the image {leaned}): not clear, so no "
                     "level answer rests on it alone; set the "
                     "polarity by hand if the overlay looks inverted")

    def leaned_on_display(self, first: Appearance, orientation: str, ahead_gc: float) -> None:
        """This verdict, clear at the clicks on the image shown ``orientation`` (the clicks turned with it), used
        instead of ``first`` (unclear at the clicks as stored, leaning the other polarity): on that display the
        image agrees with the CT ``ahead_gc`` more than as stored under either polarity, too little to take the
        display (``REFUSE_ORIENTATION_AT_CLICKS_GC``; ``appearance_checks._leaning``). Never clear: the display
        is neither taken nor ruled out, so no level answer rests on it alone; only the levels' winner, judged at the
        clicks too, can make it clear and judge the display again (``AppearanceChecks.with_winner``)."""
        self.clear = False
        self.note = (f"{self.polarity}, found only on the image {orientation.replace('-', ' ')} (GC gap "
                     f"{self.clarity_gc:.3f} there, {ahead_gc:.3f} ahead of the image as stored, where it was unclear "
                     f"and taken {first.polarity}): not clear, so no level answer rests on it alone; check the "
                     "display's orientation, and set the polarity by hand if the overlay looks inverted")

    def not_confirmed_by(self, second: Appearance) -> None:
        """This clear verdict (no clicks, the image as it is, clear by less than ``CHECKED_REFINED_GC``) no longer
        clear: the second opinion without the shading (``second``, ``REFINED_WITHOUT_SHADING``) leans the same way
        but by less than its own clear gap ``CLEAR_REFINED_GC``, so the two together are not clear evidence (seen:
        report cases 125 and 149's large patients, bone bright, taken bone dark clearly by 0.30 and 0.34, the second
        opinion bone dark by 0.09 and 0.02). The polarity stays."""
        self.clear = False
        self.note = (f"{self.note}; without its shading above {WITHOUT_SHADING_MM:g} mm the image leans the same way "
                     f"only by {second.clarity_gc:.3f} (< {second.threshold_gc:g}): not clear, so no level answer "
                     "rests on it alone; set the polarity by hand if the overlay looks inverted")

    def take_polarity_verdict(self, again: Appearance, evidence: str, threshold_gc: float) -> None:
        """Take the verdict of ``again`` on the same polarity, decided on more evidence (``decide_polarity`` with
        ``evidence``, e.g. the levels contest's winner, judged at the clicks too, where a lead of ``threshold_gc`` is
        needed): how clearly, by what, and the note."""
        if again.polarity != self.polarity:
            raise ValueError("a verdict on another polarity cannot be taken over: the image was converted as "
                             f"{self.polarity}")
        self.clear, self.clarity_gc, self.threshold_gc = again.clear, again.clarity_gc, threshold_gc
        self.decided_by, self.image_polarity = again.decided_by, again.image_polarity
        self.note = f"{again.note}; confirmed with {evidence} judged too (a lead of {threshold_gc} needed there)"
        self.scores["refined"] = again.scores.get("refined")

    def other_polarity(self, dark_storage: str, orientation_scores: dict,
                       stated: tuple[str | None, str] = (None, STORAGE_FROM_FILE)) -> Appearance:
        """A copy under the other polarity, never clear: a bone-dark image converted with ``dark_storage``, the
        storage's source under that polarity from ``stated`` (``stated_storage``), the database's orientation
        verdict from ``orientation_scores`` measured under that polarity. The levels contest
        runs on it when, under this unclear polarity, its best labelling explained the image poorly
        (``AppearanceChecks.contest_under_other_polarity``); only its winner judged at the clicks can make it clear
        (``with_winner``)."""
        polarity = next(k for k in POLARITIES if k != self.polarity)
        other = replace(self, polarity=polarity, storage=dark_storage if polarity == "bone-dark" else "log-display",
                        clear=False, scores=dict(self.scores),
                        orientation_at_clicks=None, orientation_decided_by="image (database)",
                        note=(f"{polarity}, tried because as {self.polarity} (unclear) the best labelling of the "
                              "clicks explained the image poorly; not clear"))
        other._storage_source(*stated)
        other.set_orientation(orientation_scores)
        return other

    def displayed_otherwise(self, first: Appearance, evidence: dict, orientation: str, taken_gc: float) -> None:
        """This appearance (``first.other_polarity``) taken because, at the clicks' poses, the image turned by
        ``orientation`` agrees with the CT under this polarity (``evidence``: ``click_orientation`` under it) by
        ``REFUSE_ORIENTATION_AT_CLICKS_GC`` more than the image as stored did under ``first``'s polarity
        (``taken_gc``; module docstring, ``REFINED_WITH_ORIENTATION``): this polarity, displayed ``orientation``, the
        image refused (never trusted, the polarity not called clear on its own)."""
        self.orientation_at_clicks = dict(evidence)
        self.orientation_decided_by = f"image ({REFINED_WITH_ORIENTATION})"
        self.orientation, self.orientation_clear = orientation, False
        self.decided_by, self.image_polarity, self.clear = f"image ({REFINED_WITH_ORIENTATION})", self.polarity, False
        shown = orientation.replace("-", " ")
        self.note = (f"{self.polarity}, displayed {shown}: at the clicks' poses the image {shown} as {self.polarity} "
                     f"agrees with the CT at GC {evidence['scores'][orientation]:.3f}, the image as stored as "
                     f"{first.polarity} (taken first, by a lead of {first.clarity_gc:.3f}) only at {taken_gc:.3f}: "
                     "the polarity and the display were found together, neither clear on its own")

    def set_storage(self, gc_by_storage: dict, stated: str | None = None, stated_by: str = STORAGE_FROM_FILE) -> None:
        """Record the best GC of each conversion (``database_gc``) and, for a bone-dark image, use the one stated
        (``stated``, by ``stated_by``: the file or the user; ``stated_storage``), else the better-agreeing one
        (``dark_storage``; module docstring)."""
        self.scores["storage"] = {k: float(np.max(v)) for k, v in gc_by_storage.items()}
        if self.bone_dark:
            self.storage = dark_storage(gc_by_storage, stated)
        self._storage_source(stated, stated_by)

    def _storage_source(self, stated: str | None, stated_by: str) -> None:
        """``storage_from`` under this appearance's polarity: a bone-dark image's stated storage by whom it was stated
        (else the image's), a bone-bright image used as displayed whatever was stated (a user who set a storage is
        told so)."""
        if self.bone_dark:
            self.storage_from = STORAGE_FROM_IMAGE if stated is None else stated_by
        else:
            self.storage_from = STORAGE_SET_UNUSED if stated is not None and stated_by == STORAGE_FROM_USER \
                else STORAGE_FROM_IMAGE

    def set_orientation(self, scores: dict) -> None:
        """Record ``orientation_scores`` and decide the orientation (module docstring)."""
        self.orientation_scores = dict(scores)
        lead = scores["as-stored"] - max((v for k, v in scores.items() if k != "as-stored"), default=-np.inf)
        self.orientation = database_orientation(scores)
        self.orientation_clear = bool(lead >= CLEAR_ORIENTATION_GC)

    def set_orientation_at_clicks(self, evidence: dict, clear_gc: float | None = None) -> None:
        """Decide the orientation again from the GC at the clicks' poses (``click_orientation``; ``evidence``:
        its ``as_dict()``), which replaces the database's verdict: another orientation is taken (and the image
        refused) when it leads the stored one by ``REFUSE_ORIENTATION_AT_CLICKS_GC`` with the clicks fitted
        (``displayed_rival``); the stored one is clear when it leads every judged rival, fitted or not, by
        ``clear_gc`` (None: ``CLEAR_ORIENTATION_AT_CLICKS_GC``; more when the evidence leans toward the stored
        orientation) and the database did not find another orientation clearly better (a conflict of the two is
        never clear)."""
        database_refused = self.orientation != "as-stored"  # the database's verdict, before this one
        self.orientation_at_clicks = dict(evidence)
        self.orientation_decided_by = f"image ({REFINED_AT_CLICKS})"
        scores, fitted = evidence["scores"], evidence["fitted"]
        stored = scores["as-stored"]
        judged = [o for o in scores if o != "as-stored" and np.isfinite(scores[o])]  # nan: clicks not fittable
        rival = max(judged, key=scores.get, default=None)
        lead = stored - scores[rival] if rival is not None else np.inf
        self.orientation = displayed_rival(scores, fitted, stored) or "as-stored"
        clear_gc = CLEAR_ORIENTATION_AT_CLICKS_GC if clear_gc is None else clear_gc
        self.orientation_clear = bool(lead >= clear_gc and not database_refused)

    def set_orientation_without_clicks(self, orientation: str, scores: dict) -> None:
        """Without clicks: the display taken as ``orientation`` (mirrored left-right, flipped up-down, turned 180
        degrees, or on a square detector turned a quarter and perhaps mirrored) from the refined image-alone
        registrations (``scores``: {"as-stored": GC, orientation: GC}, each the best under the polarity used), which
        ``appearance_checks._orientation_without_clicks`` does only when it leads by
        ``REFUSE_ORIENTATION_AT_CLICKS_GC``: the image is refused (module docstring)."""
        self.orientation_without_clicks = {k: float(v) for k, v in scores.items()}
        self.orientation, self.orientation_clear = orientation, False
        self.orientation_decided_by = f"image ({refined_on_without_clicks(orientation)})"

    def summary(self, turned: str = "as-stored") -> str:
        """The appearance in words, for the CLI, the window and the report: polarity (``note``), storage, and the
        orientation with how clearly and from what it was found; ``turned``: the turn the user had the file turned
        by before registering (``image.turn``; result.json ``inputs.xray_turned``), which the orientation is
        relative to."""
        where = ("at the clicks' poses" if self.orientation_at_clicks is not None else
                 f"refined on the image as stored and {self.orientation.replace('-', ' ')}"
                 if self.orientation_without_clicks is not None else
                 "on the DRR database")
        how = ", unclear" if self.orientation == "as-stored" and not self.orientation_clear else ""
        stated = STORAGE_NOTES.get(self.storage_from, "")
        shown = self.orientation.replace("-", " ")
        if turned != "as-stored":
            shown = ("as turned" if self.orientation == "as-stored" else f"{shown} of that") + \
                f" (the file shown {turned.replace('-', ' ')} as asked)"
        return (f"{self.note}; stored as {self.storage.replace('-', ' ')}{stated}; matches the CT {shown} "
                f"({where}{how})")

    def orientation_gc(self) -> tuple[float, float]:
        """(GC of the orientation taken, GC as stored) from the scores that decided it."""
        scores = (self.orientation_at_clicks["scores"] if self.orientation_at_clicks is not None
                  else self.orientation_without_clicks or self.orientation_scores)
        return float(scores[self.orientation]), float(scores["as-stored"])

    def as_dict(self) -> dict:
        return asdict(self)


def database_gc(pixels: np.ndarray, mask: np.ndarray, drrs: np.ndarray, factor: int) -> tuple[dict, dict]:
    """The image against every database DRR, in one pass (``metrics.gc_maps``):

    - polarity scores ``{"bone-dark": max_k -GC(R, D_k), "bone-bright": max_k GC(R, D_k)}`` of the rank image R;
    - ``gc_by_storage``: GC of a bone-dark image converted as linear intensity (-log) or as a log display with every
      DRR, ``{storage: (n,) scores}``; the chosen conversion's scores are the spatial stage's GC map.

    ``drrs``: (n, rows, cols) coarse DRRs (line integrals); ``factor``: detector binning to their pixel."""
    shape = drrs.shape[1:]
    coarse_mask = bin_mask_to(mask, factor, shape)
    images = [bin_image_to(rank_image(pixels, mask), factor, shape)]
    images += [bin_image_to(attenuation(pixels, mask, True, storage), factor, shape) for storage in STORAGES]
    ranked, *stored = gc_maps(images, drrs, coarse_mask)
    return ({"bone-dark": float(np.max(-ranked)), "bone-bright": float(np.max(ranked))},
            dict(zip(STORAGES, stored, strict=True)))


def stated_storage(xray, storage: str = "auto") -> tuple[str | None, str]:
    """(storage, by whom) a bone-dark image's storage is stated: the user's ``storage`` unless "auto"
    (``RegistrationParameters.storage``), else the file's (``XrayImage.stated_storage``; None: not stated, the image
    decides)."""
    if storage != "auto":
        return storage, STORAGE_FROM_USER
    return xray.stated_storage, STORAGE_FROM_FILE


def dark_storage(gc_by_storage: dict, stated: str | None = None) -> str:
    """The conversion of a bone-dark image: the one stated (``stated``: ``stated_storage``), else the one whose best
    DRR agrees more (``database_gc``; module docstring)."""
    if stated is not None:
        return stated
    return max(gc_by_storage, key=lambda k: float(np.max(gc_by_storage[k])))


def orientation_scores(pixels: np.ndarray, mask: np.ndarray, drrs_grid: np.ndarray, factor: int,
                       bone_dark: bool) -> dict:
    """score(o) for every orientation o of ``turn.ORIENTATIONS`` that keeps the image's shape (module docstring);
    ``drrs_grid``: (ny, nz, rows, cols)."""
    half = drrs_grid[::2, ::2]
    rows, cols = half.shape[2:]
    flat = half.reshape(-1, rows, cols)
    sign = -1.0 if bone_dark else 1.0
    ranked = rank_image(pixels, mask)
    out = {}
    for name in ORIENTATIONS:
        image, field = ORIENTATIONS[name](ranked), ORIENTATIONS[name](mask)
        if image.shape != ranked.shape:  # a quarter turn of an image that is not square
            continue
        coarse_mask = bin_mask_to(np.ascontiguousarray(field), factor, (rows, cols))
        g = similarity("gc", bin_image_to(np.ascontiguousarray(image), factor, (rows, cols)), flat, coarse_mask)
        out[name] = float(np.max(sign * g))
    return out


def image_polarity(scores: dict) -> tuple[str, float]:
    """The polarity with the larger score and the gap to the other."""
    dark, bright = scores["bone-dark"], scores["bone-bright"]
    return ("bone-dark" if dark >= bright else "bone-bright"), float(abs(dark - bright))


def displayed_without_clicks(stored: dict, turned: dict) -> tuple[str, dict] | None:
    """Without clicks, the display an image is shown in, from its image-alone refinements
    (``appearance_checks._orientation_without_clicks``): ``stored`` {polarity: best refined GC} on the image as
    stored, ``turned`` {orientation o: {polarity: best refined GC}} on each rival display. For each o, with p its
    leading polarity there (``image_polarity``), the lead

        turned[o][p] - stored[p]

    and the best lead reaching ``REFUSE_ORIENTATION_AT_CLICKS_GC`` gives (o, {"as-stored": stored[p], o: turned[o][p]});
    else None."""
    leads = {}
    for o, scores in turned.items():
        seen, _ = image_polarity(scores)
        leads[o] = {"as-stored": float(stored[seen]), o: float(scores[seen])}
    best = max(leads, key=lambda o: leads[o][o] - leads[o]["as-stored"], default=None)
    if best is None or leads[best][best] - leads[best]["as-stored"] < REFUSE_ORIENTATION_AT_CLICKS_GC:
        return None
    return best, leads[best]


def verdict_at_clicks(scores: dict, fits: dict, fitted_min_gc: float = FITTED_MIN_GC) -> tuple[str, float, bool]:
    """(polarity, lead, clear) from the scores at the clicks' poses (module docstring): the polarity whose best
    registration keeps the clicks fitted (``fits``: {polarity: bool}; both or neither: the higher GC), its GC
    lead over the other (negative when the other got more GC by leaving the clicks), and whether that is clear:
    a lead >= ``CLEAR_CLICKS_GC``, a GC >= ``MIN_CLICKS_GC`` and the clicks fitted. A registration with GC below
    ``fitted_min_gc`` is not preferred for keeping the clicks fitted (module docstring; another value only to
    replay recorded verdicts: ``Testing/Benchmarks/calibrate_fitted_gc.py``)."""
    seen = max(POLARITIES, key=lambda k: (bool(fits.get(k)) and scores[k] >= fitted_min_gc, scores[k]))
    lead = float(scores[seen] - max(scores[k] for k in POLARITIES if k != seen))
    return seen, lead, bool(lead >= CLEAR_CLICKS_GC and scores[seen] >= MIN_CLICKS_GC and fits.get(seen))


def decide_polarity(database: dict, refined: dict | None, requested: str, header_bone_dark: bool,
                    header_source: str, storage: dict | None = None, header_explicit: bool = False,
                    refined_by: str = REFINED_AT_DATABASE_POSES, fits: dict | None = None) -> Appearance:
    """The polarity to use (module docstring). ``requested``: "auto" or a polarity the user chose; ``storage``:
    the ``database_gc`` when known (else see ``Appearance.set_storage``); ``header_explicit``: the file states its
    polarity (rather than a default for its type); ``refined_by``: where the ``refined`` scores were measured
    (``REFINED_AT_DATABASE_POSES``, or ``REFINED_AT_CLICKS`` / ``REFINED_ON_MIRROR`` with ``fits``: {polarity: the
    best registration keeps the clicks fitted})."""
    header = "bone-dark" if header_bone_dark else "bone-bright"
    if refined is None:
        evidence, threshold, by = database, CLEAR_POLARITY_GC, "image"
    else:
        evidence, threshold, by = refined, CLEAR_REFINED_GC, f"image ({refined_by})"
    if refined is not None and measured_at_clicks(refined_by):
        threshold = CLEAR_CLICKS_GC
        seen, gap, clear = verdict_at_clicks(refined, fits or {})
        why = ("no registration of it keeps the clicks fitted" if not (fits or {}).get(seen) else
               f"GC lead {gap:.3f} < {threshold}" if gap < threshold else
               f"best GC {evidence[seen]:.3f} < {MIN_CLICKS_GC}")
    else:
        seen, gap = image_polarity(evidence)
        clear, why = gap >= threshold, f"GC gap {gap:.3f} < {threshold}"
    if requested in POLARITIES:
        polarity, by = requested, "user"
        contradicted = clear and seen != requested
        note = (f"{requested} as set by the user, but the image looks {seen} (GC gap {gap:.3f}): check the "
                "polarity setting" if contradicted else f"{requested} as set by the user")
        clear = not contradicted
    elif header_explicit and seen != header:
        polarity, by, clear = header, "header (the image disagrees)", False
        note = (f"{header} as the file states ({header_source}), but the image looks {seen} (GC gap {gap:.3f}): "
                "not trusted; check the image's polarity and the file's tags, or set the polarity by hand")
    elif header_explicit:
        polarity, clear = header, True
        note = f"{header}, as the file states ({header_source}) and the image agrees (GC gap {gap:.3f})"
    elif clear:
        polarity = seen
        note = f"{seen}, found from the {by} (GC gap {gap:.3f} >= {threshold})"
    else:
        polarity = seen
        note = (f"{seen}, but the image barely tells ({why}); the file does not state the polarity ({header} is "
                "only the default for its type): set the polarity by hand if the overlay looks inverted")
    scores = {"database": {k: database[k] for k in POLARITIES},
              "refined": None if refined is None else {k: refined[k] for k in POLARITIES}, "storage": None}
    appearance = Appearance(polarity, "log-display" if polarity == "bone-bright" else "linear-intensity", by,
                            bool(clear), gap, threshold, scores, header, header_source, seen, note)
    if storage is not None:
        appearance.set_storage(storage)
    return appearance


def fixed_appearance(polarity: str, header_bone_dark: bool, header_source: str) -> Appearance:
    """The appearance before (or without) the image's verdict: the user's polarity, else the header's."""
    header = "bone-dark" if header_bone_dark else "bone-bright"
    chosen, by = (polarity, "user") if polarity in POLARITIES else (header, "header")
    storage = "linear-intensity" if chosen == "bone-dark" else "log-display"
    return Appearance(chosen, storage, by, by == "user", float("nan"), CLEAR_POLARITY_GC, {}, header,
                      header_source, "", f"{chosen} from the {'user' if by == 'user' else 'file header'}")
